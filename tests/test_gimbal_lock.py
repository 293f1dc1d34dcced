"""Gimbal lock in all twelve Euler sequences, and quaternion extremes (half turns, near-identity,
components exactly 0 or 1, slightly non-orthogonal matrices).

tests/test_kinematics.py checks the conversions exactly at the lock and 1e-9 from it. Here the lock
is approached in a sweep -- exactly at it and within 1e-12, 1e-9 and 1e-6 of it, from both sides, in
float64 and float32 -- and what is measured (matrix round-trip errors, Jacobians against central
finite differences, the size and accuracy of the Euler-angle rates) is recorded with the ``extreme``
fixture for the published table. Every check asserts the measured number against a bound.

Compiling is the expensive part on CPU. The sweep runs eagerly (op by op), once per dtype, cached:
the twelve sequences share array shapes, so after the first sequence nearly every operation hits
JAX's per-shape cache, which is several times cheaper than compiling one program for all twelve.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import EPS32, EPS64
from scipy.spatial.transform import Rotation

import rigidjax as rj

SEQS = rj.kinematics.SEQUENCES
PROPER = np.array([rj.kinematics.is_proper_sequence(s) for s in SEQS])
CLASSES = {"proper": PROPER, "Tait-Bryan": ~PROPER}
# (phi, psi) pairs: generic, both near +-pi (phi + psi wraps), and small.
PAIRS = np.array([[0.7, -1.9], [-2.5, 2.9], [3.0, 3.1], [-0.3, 0.3]])
DELTAS = (0.0, 1e-12, 1e-9, 1e-6)
OMEGA = np.array([0.3, -1.2, 0.8])  # a generic body angular velocity (rad/s), not in the lock plane
RATES = np.array([0.5, -0.4, 1.1])
ADVICE = "keep states in quaternions; convert to Euler angles only for output"


def _locks(seq):
    return (0.0, np.pi) if rj.kinematics.is_proper_sequence(seq) else (np.pi / 2, -np.pi / 2)


def _grid():
    """Angles ``(12, M, 3)``: for each sequence, each lock, each delta and side, each (phi, psi) pair;
    and the distance ``(M,)`` from the lock of each column (the same for every sequence)."""
    columns, deltas = [], []
    for d in DELTAS:
        for lock_index in range(2):
            for side in (-1.0, 1.0) if d > 0 else (1.0,):
                for phi, psi in PAIRS:
                    columns.append((lock_index, side * d, phi, psi))
                    deltas.append(d)
    angles = np.array(
        [[[phi, _locks(seq)[i] + off, psi] for i, off, phi, psi in columns] for seq in SEQS], np.float64
    )
    return angles, np.array(deltas)


ANGLES, DELTA = _grid()
M = ANGLES.shape[1]
# Quaternions with components exactly 0 or +-1 (identity, half turns about axes and diagonals).
_h = np.sqrt(0.5)
SPECIAL_Q = np.array(
    [
        [1.0, 0, 0, 0],
        [0, 1.0, 0, 0],
        [0, 0, 1.0, 0],
        [0, 0, 0, 1.0],
        [-1.0, 0, 0, 0],
        [0, 0, -1.0, 0],
        [_h, _h, 0, 0],
        [0, _h, _h, 0],
        [0, 0, _h, -_h],
        [_h, 0, 0, -_h],
        [0.5, 0.5, 0.5, 0.5],
        [0, 0.5, -0.5, 0.5] / np.linalg.norm([0, 0.5, -0.5, 0.5]),
    ]
)
K = SPECIAL_Q.shape[0]


def _kinematics(angles, special_q):
    """Everything the value checks need, for all twelve sequences in one program.

    Per sequence and column: matrix round-trip errors through ``euler_from_matrix`` and through
    ``euler_from_quat`` (of ``q``, of ``-q``, and of the special quaternions), the angles, the
    angular velocities for ``RATES``, and ``euler_rates`` for ``OMEGA`` with the round-trip error.
    """
    out = {k: [] for k in ("err_R", "err_q", "err_neg", "err_special", "angles_R", "angles_q", "angles_neg")}
    out.update({k: [] for k in ("q", "w_body", "w_space", "rates", "rates_err", "special_angles")})
    dtype = angles.dtype
    omega = jnp.broadcast_to(jnp.asarray(OMEGA, dtype), angles.shape[1:])
    rates_in = jnp.broadcast_to(jnp.asarray(RATES, dtype), angles.shape[1:])
    R_special = rj.matrix_from_quat(special_q)

    def err(A, B):
        return jnp.max(jnp.abs(A - B), axis=(-2, -1))

    for s, seq in enumerate(SEQS):
        a = angles[s]
        R = rj.matrix_from_euler(a, seq)
        q = rj.quat_from_euler(a, seq)
        a_R = rj.euler_from_matrix(R, seq)
        a_all = rj.euler_from_quat(jnp.concatenate([q, -q, special_q]), seq)
        a_q, a_neg, a_special = a_all[:M], a_all[M : 2 * M], a_all[2 * M :]
        out["err_R"].append(err(rj.matrix_from_euler(a_R, seq), R))
        out["err_q"].append(err(rj.matrix_from_euler(a_q, seq), R))
        out["err_neg"].append(err(rj.matrix_from_euler(a_neg, seq), R))
        out["err_special"].append(err(rj.matrix_from_euler(a_special, seq), R_special))
        out["angles_R"].append(a_R)
        out["angles_q"].append(a_q)
        out["angles_neg"].append(a_neg)
        out["special_angles"].append(a_special)
        out["q"].append(q)
        w_body = rj.body_angular_velocity(a, rates_in, seq)
        w_space = rj.space_angular_velocity(a, rates_in, seq)
        out["w_body"].append(w_body)
        out["w_space"].append(w_space)
        rates = rj.euler_rates(a, omega, seq, throw=False)
        out["rates"].append(rates)
        back = rj.body_angular_velocity(a, jnp.where(jnp.isfinite(rates), rates, 0.0), seq)
        out["rates_err"].append(jnp.max(jnp.abs(back - omega), axis=-1))
    return {k: jnp.stack(v) for k, v in out.items()}


@functools.cache
def kinematics(dtype):
    # One program: eagerly, each function is a program of its own per sequence (about 110 per
    # dtype, twice the compile time); test_kinematics covers the eager calls.
    angles, special_q = jnp.asarray(ANGLES, dtype), jnp.asarray(SPECIAL_Q, dtype)
    return jax.tree.map(np.asarray, jax.jit(_kinematics)(angles, special_q))


def _wrapped(d):
    return np.abs((d + np.pi) % (2 * np.pi) - np.pi)


# ----------------------------------------------------------------------------------------------
# 1. The rotation is reproduced, in float64 and float32
# ----------------------------------------------------------------------------------------------


ANGLE_CASES = {
    # dtype: (bound, what the row says)
    np.float64: (1.2e-15, "finite angles; matrix_from_euler(euler_from_matrix/quat(R)) reproduces R"),
    np.float32: (4e-7, "finite angles; matrix reproduced to float32 roundoff"),
}


# The float32 sweep (a second program of every operation) runs in the full run only.
FLOAT32 = pytest.param(np.float32, marks=pytest.mark.slow, id="float32")


@pytest.mark.parametrize("dtype", [pytest.param(np.float64, id="float64"), FLOAT32])
def test_angles_reproduce_the_rotation(dtype, extreme):
    bound, behaviour = ANGLE_CASES[dtype]
    k = kinematics(dtype)
    for key in ("angles_R", "angles_q", "angles_neg", "q", "w_body", "special_angles"):
        assert k[key].dtype == dtype and np.all(np.isfinite(k[key])), key
    for cls, rows in CLASSES.items():
        for d in DELTAS:
            cols = DELTA == d
            err = max(k["err_R"][rows][:, cols].max(), k["err_q"][rows][:, cols].max())
            where = "exactly at" if d == 0 else f"within {d:g} of"
            assert err <= bound, (cls, d, err)
            extreme(
                "gimbal lock",
                f"{cls} sequences, theta {where} the lock ({np.dtype(dtype).name})",
                behaviour,
                err,
                bound,
                ADVICE,
            )


# ----------------------------------------------------------------------------------------------
# 2. Angular velocity and Euler-angle rates near the lock
# ----------------------------------------------------------------------------------------------


def _reference_omega():
    """Body and space angular velocity for ``RATES`` at ``ANGLES``, from scipy rotations (float64):
    ``omega = phi' u1 + theta' u2 + psi' u3`` with ``u3 = e_c``, ``u2 = R_c(psi)^T e_b`` and
    ``u1 = (R_b(theta) R_c(psi))^T e_a`` for ``seq = "abc"``."""
    body, space = [], []
    for s, seq in enumerate(SEQS):
        e = [np.eye(3)["xyz".index(c)] for c in seq]
        Rb = Rotation.from_rotvec(ANGLES[s, :, 1:2] * e[1])
        Rc = Rotation.from_rotvec(ANGLES[s, :, 2:3] * e[2])
        u = [(Rb * Rc).inv().apply(e[0]), Rc.inv().apply(e[1]), np.broadcast_to(e[2], (M, 3))]
        w = sum(RATES[i] * u[i] for i in range(3))
        body.append(w)
        space.append(Rotation.from_euler(seq.upper(), ANGLES[s]).apply(w))
    return np.array(body), np.array(space)


@pytest.mark.parametrize("dtype", [pytest.param(np.float64, id="float64"), FLOAT32])
def test_angular_velocity_near_lock(dtype, extreme):
    k = kinematics(dtype)
    eps = EPS64 if dtype == np.float64 else EPS32
    body, space = _reference_omega()
    assert np.all(np.isfinite(k["w_body"])) and np.all(np.isfinite(k["w_space"]))
    err = max(np.abs(k["w_body"] - body).max(), np.abs(k["w_space"] - space).max())
    print(dtype, "omega", err, err / eps)
    bound = 8 * eps
    assert err <= bound
    extreme(
        "gimbal lock",
        f"body/space_angular_velocity at and near the lock, all sequences ({np.dtype(dtype).name})",
        "smooth maps: finite, match scipy-built references to roundoff",
        err,
        bound,
        "none needed: angles -> omega has no singularity",
    )


@pytest.mark.slow
def test_euler_rates_near_lock_float64(extreme):
    """The rates grow like 1/delta (the truth) and reproduce omega to about eps/delta; exactly at the
    lock an omega with a component the angles cannot follow gives NaN (throw=False) or an error."""
    k = kinematics(np.float64)
    rates, err = k["rates"], k["rates_err"]
    at = DELTA == 0
    assert np.all(np.isnan(rates[:, at]))
    for d in DELTAS[1:]:
        cols = DELTA == d
        assert np.all(np.isfinite(rates[:, cols]))
        size = np.abs(rates[:, cols]).max(axis=-1)
        e = err[:, cols].max()
        print("rates", d, size.min() * d, size.max() * d, e, e * d / EPS64)
        # ~ |omega . n| / delta, with n the normal of the followable plane (which turns with psi).
        assert size.min() >= 1e-3 / d and 0.1 / d <= size.max() <= 10 / d
        bound = 4 * EPS64 / d
        assert e <= bound
        extreme(
            "gimbal lock",
            f"euler_rates, theta within {d:g} of the lock (float64), generic omega",
            f"finite rates of size ~|omega|/delta ({size.max():.1e} rad/s); "
            "body_angular_velocity(rates) reproduces omega to ~eps/delta",
            e,
            bound,
            "integrate quaternions, not Euler angles, through the lock",
        )
    extreme(
        "gimbal lock",
        "euler_rates exactly at the lock, omega off the followable plane",
        "raises (throw=True) or NaN rates (throw=False); omega in the plane: split psi' = 0",
        advice="integrate quaternions, not Euler angles, through the lock",
    )
    with pytest.raises(Exception, match="gimbal lock"):
        jax.block_until_ready(rj.euler_rates(ANGLES[0, 0], OMEGA, SEQS[0]))


@pytest.mark.slow
def test_euler_rates_near_lock_float32(extreme):
    """In float32 a lock within 16 eps (~2e-6) of the determinant counts as exact."""
    k = kinematics(np.float32)
    rates = k["rates"]
    for d in DELTAS:
        cols = DELTA == d
        print("f32 rates", d, np.isnan(rates[:, cols]).mean())
    assert np.all(np.isnan(rates[:, DELTA < 2e-6]))
    extreme(
        "gimbal lock",
        "euler_rates in float32, theta within 1e-6 of the lock",
        "treated as exactly locked (|det| <= 16 eps32 ~ 2e-6): NaN (throw=False) or an error for a "
        "generic omega",
        advice="use float64 or quaternions near the lock",
    )


# ----------------------------------------------------------------------------------------------
# 3. Gradients near the lock: finite, jacfwd = jacrev, and central finite differences
# ----------------------------------------------------------------------------------------------


@functools.cache
def quat_jacobians(dtype, reverse=True):
    """``jacfwd`` (and ``jacrev``) of ``euler_from_quat`` at every sweep point, ``(12, M, 3, 4)``."""

    @jax.jit  # one program (eagerly, every operation of every sequence was a program of its own)
    def jacobians(q):
        fwd, rev = [], []
        for s, seq in enumerate(SEQS):
            f = functools.partial(rj.euler_from_quat, seq=seq)
            fwd.append(jax.vmap(jax.jacfwd(f))(q[s]))
            if reverse:
                rev.append(jax.vmap(jax.jacrev(f))(q[s]))
        return jnp.stack(fwd), jnp.stack(rev) if reverse else None

    fwd, rev = jacobians(jnp.asarray(kinematics(dtype)["q"]))
    return np.asarray(fwd), None if rev is None else np.asarray(rev)


@pytest.mark.slow
def test_gradients_finite_and_consistent_float64(extreme):
    fwd, rev = quat_jacobians(np.float64)
    assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
    for d in DELTAS:
        cols = DELTA == d
        scale = np.abs(fwd[:, cols]).max(axis=(-2, -1), keepdims=True)
        rel = (np.abs(fwd[:, cols] - rev[:, cols]) / scale).max()
        print("fwd-rev", d, rel, scale.max())
        bound = 1e-12
        assert rel <= bound
    extreme(
        "gimbal lock",
        "jacfwd and jacrev of euler_from_quat at and within 1e-12..1e-6 of the lock (float64)",
        "finite; jacfwd = jacrev; |J| ~ 1/delta (d phi/dq, d psi/dq)",
        rel,
        bound,
        "differentiate through quaternions; Euler-angle gradients blow up like 1/delta near the lock",
    )


@pytest.mark.slow
def test_gradients_match_finite_differences_near_lock(extreme):
    """Away from the exact lock the map q -> angles is smooth, with derivatives ~ 1/delta: central
    differences with the step ``h = (eps delta^2)^(1/3)`` that balances truncation and roundoff."""
    k = kinematics(np.float64)
    fwd, _ = quat_jacobians(np.float64)
    # (phi, psi) pairs whose angles stay clear of the +-pi wrap under the perturbation.
    pair = np.tile(np.arange(len(PAIRS)), M // len(PAIRS))
    for d in DELTAS[1:]:
        cols = np.flatnonzero((DELTA == d) & np.isin(pair, [0, 3]))
        h = (EPS64 * d * d) ** (1 / 3)
        worst = 0.0
        for s, seq in enumerate(SEQS):
            q = k["q"][s, cols]
            steps = h * np.eye(4)
            x = np.concatenate([q[:, None, :] + steps, q[:, None, :] - steps]).reshape(-1, 4)
            a = np.asarray(rj.euler_from_quat(x, seq)).reshape(2, len(cols), 4, 3)
            fd = np.swapaxes((a[0] - a[1]) / (2 * h), -1, -2)  # (cols, 3, 4)
            J = fwd[s, cols]
            assert np.abs(k["angles_q"][s, cols][:, [0, 2]]).max() < np.pi - 0.05
            rel = (np.abs(fd - J).max(axis=(-2, -1)) / np.abs(J).max(axis=(-2, -1))).max()
            worst = max(worst, rel)
        print("fd", d, h, worst)
        bound = {1e-6: 2e-6, 1e-9: 2e-4, 1e-12: 2e-2}[d]  # measured ~6e-7, 6e-5, 6e-3
        assert worst <= bound
        extreme(
            "gimbal lock",
            f"d(angles)/dq within {d:g} of the lock vs central differences (step {h:.0e}), float64",
            "jacfwd agrees with finite differences (relative to max|J| ~ 1/delta)",
            worst,
            bound,
            "expect gradients of size 1/delta; clip or reparametrise if they feed an optimiser",
        )


@jax.jit
def _matrix_path_jacobians(angles):
    out = []
    for s in (SEQS.index("zxz"), SEQS.index("zyx")):
        R = rj.matrix_from_euler(angles[s], SEQS[s])
        f = functools.partial(rj.euler_from_matrix, seq=SEQS[s])
        out.append((jax.vmap(jax.jacfwd(f))(R), jax.vmap(jax.jacrev(f))(R)))
    return out


@pytest.mark.slow
def test_euler_from_matrix_gradients_at_lock():
    """The matrix path is quat_from_matrix (shared by all sequences) then euler_from_quat: finite
    jacfwd = jacrev on one proper and one Tait-Bryan sequence at every sweep point."""
    for fwd, rev in _matrix_path_jacobians(ANGLES):
        fwd, rev = np.asarray(fwd), np.asarray(rev)
        assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
        scale = np.abs(fwd).max(axis=(-3, -2, -1), keepdims=True)
        assert (np.abs(fwd - rev) / scale).max() <= 1e-12


@pytest.mark.slow
def test_gradients_finite_float32(extreme):
    fwd, _ = quat_jacobians(np.float32, reverse=False)  # (float32 jacrev: tests/test_kinematics.py)
    assert fwd.dtype == np.float32
    assert np.all(np.isfinite(fwd))
    print("f32 max|J|", np.abs(fwd).max())
    extreme(
        "gimbal lock",
        "jacfwd of euler_from_quat at and near the lock (float32)",
        f"finite (max |J| = {np.abs(fwd).max():.1e}); within ~1e-6 of the lock treated as locked",
        advice="use float64 for gradients near the lock",
    )


# ----------------------------------------------------------------------------------------------
# 4. Quaternion extremes
# ----------------------------------------------------------------------------------------------


def _quat_distance(p, q):
    """Distance between quaternions up to sign (``q`` and ``-q`` are one rotation)."""
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    return np.minimum(np.abs(p - q).max(axis=-1), np.abs(p + q).max(axis=-1))


def test_q_and_minus_q_give_the_same_angles(extreme):
    k = kinematics(np.float64)
    diff = _wrapped(k["angles_neg"] - k["angles_q"]).max()
    err = k["err_neg"].max()
    print("q vs -q", diff, err)
    assert diff <= 2e-15 and err <= 1.2e-15
    q = k["q"].reshape(-1, 4)
    np.testing.assert_array_equal(rj.matrix_from_quat(q), rj.matrix_from_quat(-q))
    np.testing.assert_array_equal(rj.quat_rotate(q, OMEGA), rj.quat_rotate(-q, OMEGA))
    extreme(
        "quaternions",
        "q and -q, all sweep points and sequences (float64)",
        "the same Euler angles (mod 2 pi), matrix and rotated vectors",
        diff,
        2e-15,
    )


def test_quaternions_with_exact_zero_and_one_components(extreme):
    k = kinematics(np.float64)
    err_angles = k["err_special"].max()  # euler_from_quat, all 12 sequences
    R = np.asarray(rj.matrix_from_quat(SPECIAL_Q))
    ref = Rotation.from_quat(SPECIAL_Q, scalar_first=True).as_matrix()
    err_matrix = np.abs(R - ref).max()
    err_back = _quat_distance(rj.quat_from_matrix(R), SPECIAL_Q).max()
    print("special", err_angles, err_matrix, err_back)
    assert err_angles <= 1e-15 and err_matrix <= 4e-16 and err_back <= 2e-16
    # Axis-aligned half turns give exact 0/+-1 matrices.
    np.testing.assert_array_equal(R[1], np.diag([1.0, -1.0, -1.0]))
    for fwd, rev in (
        _rotation_jacobians(R),
        _rotation_jacobians(np.asarray(rj.matrix_from_quat(-SPECIAL_Q))),
    ):
        fwd, rev = np.asarray(fwd), np.asarray(rev)
        assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
        np.testing.assert_allclose(fwd, rev, atol=1e-14)
    # Where w > 0 the round trip is smooth and its Jacobian is the unit sphere's tangent projector
    # I - q q^T; at quarter turns two of Shepperd's branches tie (the derivative averaged them).
    round_trip = jax.vmap(jax.jacfwd(lambda q: rj.quat_from_matrix(rj.matrix_from_quat(q))))
    q = SPECIAL_Q[SPECIAL_Q[:, 0] > 0]
    projector = np.eye(4) - q[:, :, None] * q[:, None, :]
    np.testing.assert_allclose(round_trip(q), projector, atol=1e-15)
    extreme(
        "quaternions",
        "components exactly 0 or +-1 (identity, half turns about axes and diagonals)",
        "euler_from_quat (12 sequences), matrix_from_quat, quat_from_matrix exact to roundoff; "
        "quat_from_matrix: finite jacfwd = jacrev, the tangent projector where two branches tie",
        max(err_angles, err_matrix, err_back),
        1e-15,
    )


_rng = np.random.default_rng(8)
# As many axes as special quaternions, so that the jitted Jacobians below compile once.
_AXES = np.concatenate(
    [np.eye(3), [[1, 1, 0], [0, 1, -1], [1, -2, 3], [-1, -1, -1]], _rng.normal(size=(K - 7, 3))]
)
_AXES /= np.linalg.norm(_AXES, axis=-1, keepdims=True)


@jax.jit
def _rotation_jacobians(R):
    """``jacfwd`` and ``jacrev`` of ``quat_from_matrix``, per matrix."""
    return jax.vmap(jax.jacfwd(rj.quat_from_matrix))(R), jax.vmap(jax.jacrev(rj.quat_from_matrix))(R)


@pytest.mark.parametrize("offset", [0.0, 1e-12, 1e-9, 1e-6])
def test_quat_from_matrix_half_turns(offset, extreme):
    """Rotations by pi (trace = -1, w = 0) and just short of it: Shepperd's branch on the largest
    component keeps the result exact; the sign is w >= 0, so at w = 0 itself q or -q may come back."""
    rot = Rotation.from_rotvec((np.pi - offset) * _AXES)
    R = rot.as_matrix()
    q = np.asarray(rj.quat_from_matrix(R))
    err = _quat_distance(q, rot.as_quat(scalar_first=True)).max()
    err_R = np.abs(np.asarray(rj.matrix_from_quat(q)) - R).max()
    print("half turn", offset, err, err_R)
    bound = 4e-16
    assert err <= bound and err_R <= 1e-15
    assert np.all(q[:, 0] >= 0) and np.abs(np.linalg.norm(q, axis=-1) - 1).max() <= 2.3e-16
    fwd, rev = (np.asarray(j) for j in _rotation_jacobians(R))
    angle_text = "pi" if offset == 0 else f"pi - {offset:g}"
    assert np.all(np.isfinite(fwd)) and np.all(np.isfinite(rev))
    np.testing.assert_allclose(fwd, rev, atol=1e-14)
    extreme(
        "quaternions",
        f"quat_from_matrix of a rotation by {angle_text} (trace ~ -1), {K} axes",
        "exact to roundoff, unit, finite gradients (q may flip sign at w = 0: both are the rotation)",
        err,
        bound,
        "compare quaternions up to sign",
    )


@pytest.mark.parametrize("angle", [1e-15, 1e-12, 1e-9, 1e-6])
def test_quat_from_matrix_near_identity(angle, extreme):
    """Small rotations keep their relative accuracy: the vector part comes from the antisymmetric
    part of R, not from 1 - trace."""
    R = Rotation.from_rotvec(angle * _AXES).as_matrix()
    q = np.asarray(rj.quat_from_matrix(R))
    exact = np.concatenate([np.full((len(_AXES), 1), np.cos(angle / 2)), np.sin(angle / 2) * _AXES], axis=-1)
    rel = (np.abs(q[:, 1:] - exact[:, 1:]).max(axis=-1) / np.sin(angle / 2)).max()
    print("near identity", angle, rel)
    bound = 4 * EPS64
    assert rel <= bound and np.abs(q[:, 0] - exact[:, 0]).max() <= EPS64
    # Smooth here: jacfwd matches central differences (entrywise, step 1e-7: inside the tolerance).
    J = np.asarray(_rotation_jacobians(R)[0])[:3]
    h = 1e-7
    steps = h * np.eye(9).reshape(9, 3, 3)
    x = np.concatenate([R[:3, None] + steps, R[:3, None] - steps]).reshape(-1, 3, 3)
    qs = np.asarray(rj.quat_from_matrix(x)).reshape(2, 3, 9, 4)
    fd = np.moveaxis((qs[0] - qs[1]) / (2 * h), -1, 1).reshape(J.shape)
    np.testing.assert_allclose(J, fd, atol=1e-8)
    extreme(
        "quaternions",
        f"quat_from_matrix near identity, rotation angle {angle:g}",
        "vector part to relative accuracy (no 1 - cos cancellation); jacfwd = finite differences",
        rel,
        bound,
    )


@pytest.mark.parametrize("size", [1e-12, 1e-9, 1e-7])
def test_quat_from_matrix_tiny_non_orthogonality(size, extreme):
    """A matrix off a rotation by ``size`` (inside the 1e-6 tolerance) gives a unit quaternion whose
    rotation is within a small multiple of ``size`` of it."""
    rng = np.random.default_rng(9)
    R = Rotation.random(K, rng=rng).as_matrix()
    noisy = R + size * rng.uniform(-1, 1, R.shape)
    q = np.asarray(rj.quat_from_matrix(noisy))
    assert np.abs(np.linalg.norm(q, axis=-1) - 1).max() <= 2.3e-16
    ratio = np.abs(np.asarray(rj.matrix_from_quat(q)) - R).max() / size
    angles_ok = np.asarray(rj.euler_from_matrix(noisy, "zxz"))
    assert np.all(np.isfinite(angles_ok))
    print("non-orthogonal", size, ratio)
    bound = 3.0
    assert ratio <= bound
    extreme(
        "quaternions",
        f"quat_from_matrix of a rotation perturbed by {size:g} (entrywise)",
        "accepted (tolerance 1e-6 in float64); unit quaternion within ratio*size of the rotation",
        ratio,
        bound,
        "orthonormalise matrices that drift by more than 1e-6",
    )
