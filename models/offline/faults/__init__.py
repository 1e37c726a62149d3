"""Fault injection for robustness studies: small pure functions, arrays in, arrays out.

touch    acceleration faults (noise at an SNR, clipping, dropouts, gaps, sample-rate
         mismatch, sensor orientation, bias, drift) and the speed/force scaling of a
         stroke's trajectory (re-rendered from the texture's vibration model)
camera   image faults (blur, exposure, noise, JPEG, rotation, distance, occlusion)
catalog  the named faults of the study, each with its strengths from mild to severe

Every function raises ValueError on a strength outside its meaningful range. Nothing here
imports torch; the service can use the same functions in its fault tests.
"""
