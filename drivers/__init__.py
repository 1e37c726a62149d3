"""Sensor sources (serial, USB, camera, replay, simulated) and the robot-side streaming client."""
