"""Quaternion and continuous 6-D rotation utilities for numpy arrays and torch tensors.

Conventions (HumanML3D's ``common/quaternion.py``):

- quaternions are ``(w, x, y, z)`` with the Hamilton product; ``qrot(q, v)`` rotates ``v`` by ``q``;
- rotation matrices act on column vectors, ``v' = R @ v``;
- the continuous 6-D representation (Zhou et al. 2019) is the first column of ``R`` followed by
  its second column; decoding is ``x = n(a)``, ``z = n(x × b)``, ``y = z × x``, ``R = [x y z]``.

Every function accepts numpy arrays or torch tensors and returns the same kind. Torch versions
are batched over any leading dimensions, broadcast like elementwise ops and are differentiable.
When arguments are mixed, numpy arguments are converted to the torch argument's dtype/device.
"""

from __future__ import annotations

from types import ModuleType
from typing import TypeAlias

import numpy as np
import torch

Array: TypeAlias = np.ndarray | torch.Tensor


def _xp(*xs: Array) -> ModuleType:
    """The array module (``numpy`` or ``torch``) of the arguments: torch if any is a tensor."""
    return torch if any(isinstance(x, torch.Tensor) for x in xs) else np


def as_like(x: Array | float, like: Array) -> Array:
    """``x`` as a tensor with ``like``'s dtype/device if ``like`` is a tensor; tensors pass through."""
    if isinstance(x, torch.Tensor):
        return x
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(np.asarray(x), dtype=like.dtype, device=like.device)
    return np.asarray(x)


def _cross(a: Array, b: Array) -> Array:
    """Cross product over the last axis, broadcasting leading axes."""
    if isinstance(a, torch.Tensor):
        a, b = torch.broadcast_tensors(a, as_like(b, a))
        return torch.linalg.cross(a, b, dim=-1)
    return np.cross(a, b)


def _norm(v: Array) -> Array:
    """Euclidean norm over the last axis, keeping it: (..., n) -> (..., 1)."""
    return ((v * v).sum(-1, keepdims=True)) ** 0.5


def normalize(v: Array) -> Array:
    """(..., n) -> (..., n) divided by its norm (no epsilon, as the reference)."""
    return v / _norm(v)


def qmul(q: Array, r: Array) -> Array:
    """Hamilton product ``q ⊗ r`` of (..., 4) quaternions (broadcasting) -> (..., 4)."""
    xp = _xp(q, r)
    q, r = as_like(q, r), as_like(r, q)
    w1, x1, y1, z1 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    w2, x2, y2, z2 = r[..., 0], r[..., 1], r[..., 2], r[..., 3]
    return xp.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def qinv(q: Array) -> Array:
    """Conjugate ``(w, -x, -y, -z)`` of (..., 4) quaternions: the inverse of a unit quaternion."""
    sign = as_like(np.array([1.0, -1.0, -1.0, -1.0]), q)
    return q * sign


def qrot(q: Array, v: Array) -> Array:
    """Rotate (..., 3) vectors by (..., 4) unit quaternions (broadcasting) -> (..., 3).

    ``v' = v + 2 (w (u × v) + u × (u × v))`` with ``u`` the vector part of ``q``.
    """
    q, v = as_like(q, v), as_like(v, q)
    u = q[..., 1:]
    uv = _cross(u, v)
    uuv = _cross(u, uv)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def qbetween(u: Array, v: Array) -> Array:
    """Shortest-arc unit quaternion rotating direction ``u`` onto ``v``: (..., 3) x2 -> (..., 4).

    Reference formula (HumanML3D ``qbetween``): ``normalize([|u||v| + u·v, u × v])``; the inputs
    need not be unit length. For exactly opposite directions, where the formula is 0/0, this
    returns a half turn about an axis perpendicular to ``u`` instead of NaN.
    """
    xp = _xp(u, v)
    u, v = as_like(u, v), as_like(v, u)
    uv_norm = (((u * u).sum(-1, keepdims=True)) * ((v * v).sum(-1, keepdims=True))) ** 0.5
    w = uv_norm + (u * v).sum(-1, keepdims=True)
    q = xp.concatenate([w, _cross(u, v)], -1)
    qn = _norm(q)
    degenerate = qn <= 1e-9 * uv_norm
    if not bool(degenerate.any()):
        return q / qn
    # Half turn about u × e, e the basis axis least aligned with u.
    ux = xp.abs(u[..., :1]) < 0.9 * _norm(u)
    e = xp.where(ux, as_like(np.array([1.0, 0.0, 0.0]), u), as_like(np.array([0.0, 1.0, 0.0]), u))
    axis = _cross(u, e)
    half_turn = xp.concatenate([xp.zeros_like(w), axis / _norm(axis)], -1)
    safe_qn = xp.where(degenerate, xp.ones_like(qn), qn)
    return xp.where(degenerate, half_turn, q / safe_qn)


def quat_to_matrix(q: Array) -> Array:
    """(..., 4) quaternions -> (..., 3, 3) rotation matrices (q is normalised first)."""
    xp = _xp(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / (q * q).sum(-1)
    rows = [
        [1.0 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1.0 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1.0 - s * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(row, -1) for row in rows], -2)


def matrix_to_quat(m: Array) -> Array:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions with ``w >= 0``.

    Shepperd's method: of the four algebraically equivalent formulas, each frame uses the one
    whose pivot (4w², 4x², 4y² or 4z²) is largest, which keeps it accurate and differentiable.
    """
    xp = _xp(m)
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    pivots = xp.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22],
        -1,
    )
    # 2 * (the pivot component), clamped so that unused candidates stay finite.
    r = xp.clip(pivots, 1e-12, None) ** 0.5
    candidates = xp.stack(
        [
            xp.stack([r[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1) / (2.0 * r[..., 0:1]),
            xp.stack([m21 - m12, r[..., 1] ** 2, m01 + m10, m02 + m20], -1) / (2.0 * r[..., 1:2]),
            xp.stack([m02 - m20, m01 + m10, r[..., 2] ** 2, m12 + m21], -1) / (2.0 * r[..., 2:3]),
            xp.stack([m10 - m01, m02 + m20, m12 + m21, r[..., 3] ** 2], -1) / (2.0 * r[..., 3:4]),
        ],
        -2,
    )  # (..., 4 candidates, 4)
    best = xp.argmax(pivots, -1)[..., None, None]
    if xp is torch:
        q = torch.take_along_dim(candidates, best, dim=-2)[..., 0, :]
    else:
        q = np.take_along_axis(candidates, best, axis=-2)[..., 0, :]
    q = q / _norm(q)
    return xp.where(q[..., :1] < 0, -q, q)


def matrix_to_cont6d(m: Array) -> Array:
    """(..., 3, 3) -> (..., 6): first column then second column (reference A.3 step 7)."""
    xp = _xp(m)
    return xp.concatenate([m[..., :, 0], m[..., :, 1]], -1)


def cont6d_to_matrix(d6: Array) -> Array:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt: ``x = n(a)``, ``z = n(x × b)``, ``y = z × x``.

    Any (non-degenerate) 6-D vector decodes to a proper rotation, columns ``[x y z]``.
    """
    xp = _xp(d6)
    x = normalize(d6[..., :3])
    z = normalize(_cross(x, d6[..., 3:]))
    y = _cross(z, x)
    return xp.stack([x, y, z], -1)


def quat_to_cont6d(q: Array) -> Array:
    """(..., 4) quaternions -> (..., 6) continuous 6-D rotations."""
    return matrix_to_cont6d(quat_to_matrix(q))


def cont6d_to_quat(d6: Array) -> Array:
    """(..., 6) continuous 6-D rotations -> (..., 4) unit quaternions with ``w >= 0``."""
    return matrix_to_quat(cont6d_to_matrix(d6))


def axis_angle_to_quat(aa: Array) -> Array:
    """(..., 3) axis-angle vectors (axis * angle in radians) -> (..., 4) unit quaternions.

    Uses ``sin(θ/2)/θ`` with its Taylor expansion near 0, so it is smooth at the identity.
    """
    xp = _xp(aa)
    angle = _norm(aa)
    small = angle < 1e-6
    safe = xp.where(small, xp.ones_like(angle), angle)
    sinc_half = xp.where(small, 0.5 - angle * angle / 48.0, xp.sin(safe / 2.0) / safe)
    return xp.concatenate([xp.cos(angle / 2.0), aa * sinc_half], -1)


def axis_angle_to_matrix(aa: Array) -> Array:
    """(..., 3) axis-angle vectors -> (..., 3, 3) rotation matrices."""
    return quat_to_matrix(axis_angle_to_quat(aa))


def yaw_to_quat(angle: Array) -> Array:
    """(...,) rotation angles about +y (radians) -> (..., 4) quaternions ``(cos θ/2, 0, sin θ/2, 0)``."""
    xp = _xp(angle)
    half = angle / 2.0
    zero = xp.zeros_like(half)
    return xp.stack([xp.cos(half), zero, xp.sin(half), zero], -1)
