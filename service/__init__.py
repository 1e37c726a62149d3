"""The real-time service: FastAPI app, sessions, async pipeline, broker, operator console, CLI root."""
