"""What the tool's sensors record while it strokes a texture.

The vibration model gives the acceleration along the surface normal; the tool
also vibrates along the stroke (an independent realisation, weaker). Where the
model has a macro surface profile (texture_library.surface), the tip rides over
its bumps: their position-periodic acceleration z''(x)·v² + z'(x)·v̇ adds to the
normal axis, and the hand–tool spring they compress adds TOOL_STIFFNESS_N_PER_MM·z to
the normal force (a random phase per stroke: the tool starts somewhere on the surface).
The accelerometer is mounted at an arbitrary fixed orientation, feels gravity and
adds noise. The force sensor sees the normal force and Coulomb friction μ·F_n
against the direction of motion (so |tangential| / normal = μ: stickiness is in
the force signal). Both the dataset builders and the simulated robot use this one
function.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texture_library.synthesis import render
from texture_library.trajectory import Trajectory
from texture_library.vibration import VibrationModel

GRAVITY = 9.80665  # m/s²
#: stiffness of the hand–tool spring between the force sensor's holder and the tip, N/mm: riding
#: over a bump of height z (relative to the profile's mean) adds TOOL_STIFFNESS_N_PER_MM·z of normal force
TOOL_STIFFNESS_N_PER_MM = 0.5
MIN_CONTACT_N = 0.05  # the tip never quite leaves the surface


@dataclass(frozen=True)
class StrokeSignals:
    """accel: (n, 3) m/s² (sensor frame); force: (n, 3) N (tangential x, tangential y, normal);
    speed: (n,) mm/s; position: (n,) mm; all at rate_hz."""

    accel: np.ndarray
    force: np.ndarray
    speed: np.ndarray
    position: np.ndarray
    rate_hz: float


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random 3×3 rotation matrix (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def stroke(
    model: VibrationModel,
    trajectory: Trajectory,
    rng: np.random.Generator,
    *,
    tangential_ratio: float = 0.5,
    noise_std: float = 0.05,
    force_noise_std: float = 0.01,
    rotation: np.ndarray | None = None,
) -> StrokeSignals:
    """Sensor signals for one stroke of `model` along `trajectory` (rendered at the model's rate)."""
    if abs(trajectory.rate_hz - model.rate_hz) > 1e-9:
        raise ValueError(f"trajectory rate {trajectory.rate_hz} Hz differs from the model's {model.rate_hz} Hz")
    normal = render(model, trajectory.speed, trajectory.force, rng)
    along = tangential_ratio * render(model, trajectory.speed, trajectory.force, rng)
    n = normal.size
    # Tool frame: x along the stroke, y across it, z the surface normal.
    tool = np.stack([along, np.zeros(n), normal], axis=1)
    tool[:, 2] += GRAVITY
    rot = random_rotation(rng) if rotation is None else np.asarray(rotation, float)
    accel = tool @ rot.T + noise_std * rng.standard_normal((n, 3))
    # Direction of motion from the backward step: position[i] − position[i−1] is the motion *into*
    # sample i, so its sign is exact at a reversal (a central difference straddles it and can
    # come out 0 or wrong there). The first sample takes the second's direction.
    direction = np.ones(n)
    if n > 1:
        direction = np.sign(np.diff(trajectory.position, prepend=trajectory.position[0]))
        direction[0] = direction[1]
    force_noise = force_noise_std * rng.standard_normal((n, 3))
    normal_force = trajectory.force
    if model.surface is not None:
        # drawn last, and only for models with a profile, so models without one render as before
        x = trajectory.position + rng.uniform(0.0, model.surface.bump_period_mm)
        bumps = model.surface.normal_accel(x, direction * trajectory.speed, trajectory.rate_hz)
        accel += bumps[:, None] * rot[:, 2][None, :]  # along the tool's z axis, in the sensor frame
        # the tip rides the bumps; the hand holding the tool does not, so its spring is compressed by them
        lift = model.surface.height(x) - 0.5 * model.surface.bump_height_mm
        normal_force = np.maximum(normal_force + TOOL_STIFFNESS_N_PER_MM * lift, MIN_CONTACT_N)
    friction = -model.mu * normal_force * direction
    force = np.stack([friction, np.zeros(n), normal_force], axis=1) + force_noise
    return StrokeSignals(accel, force, trajectory.speed.copy(), trajectory.position.copy(), trajectory.rate_hz)
