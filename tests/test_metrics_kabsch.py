"""Kabsch RMSD against independent references: a brute-force search over the rotation angle, an SVD
Kabsch with the det correction, hand-built rigid motions, and scipy's align_vectors where no reflection
fits better (on points at z = 0 it may answer with an in-plane reflection, issue 2)."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from degusta_learn.metrics import kabsch_rmsd, kabsch_rmsd_batch, kabsch_transform, unregistered_rmsd


def rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def brute_force_rmsd(p, q, n_angles=7200):
    """Min over proper rotations by grid search + local refinement; translation = centroid difference."""
    pc, qc = p - p.mean(0), q - q.mean(0)

    def rmsd(theta):
        return np.sqrt(((qc @ rot(theta).T - pc) ** 2).sum() / len(p))

    grid = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    c, s = np.cos(grid)[:, None], np.sin(grid)[:, None]  # (A, 1)
    rx, ry = c * qc[:, 0] - s * qc[:, 1], s * qc[:, 0] + c * qc[:, 1]  # (A, N)
    best = grid[np.argmin(((rx - pc[:, 0]) ** 2 + (ry - pc[:, 1]) ** 2).sum(1))]
    step = 2 * np.pi / n_angles
    res = minimize_scalar(rmsd, bounds=(best - step, best + step), method="bounded",
                          options={"xatol": 1e-12})
    return min(res.fun, rmsd(best))


def svd_kabsch_rmsd(p, q, reflections=False):
    """Textbook Kabsch via SVD; with reflections=True the det correction is skipped."""
    pc, qc = p - p.mean(0), q - q.mean(0)
    u, _, vt = np.linalg.svd(qc.T @ pc)
    d = 1.0 if reflections else np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return np.sqrt(((qc @ r.T - pc) ** 2).sum() / len(p))


def test_random_sets_match_brute_force_and_svd():
    rng = np.random.default_rng(0)
    for _ in range(60):
        n = int(rng.integers(2, 9))
        p, q = rng.random((n, 2)), rng.random((n, 2))
        ours = kabsch_rmsd(p, q)
        assert ours == pytest.approx(brute_force_rmsd(p, q), abs=1e-9)
        assert ours == pytest.approx(svd_kabsch_rmsd(p, q), abs=1e-9)


def test_hand_built_rigid_motions_give_zero():
    rng = np.random.default_rng(1)
    p = rng.random((6, 2))
    for theta in (0.0, 0.3, np.pi / 2, np.pi, -2.0, 5.9):
        q = p @ rot(theta).T + np.array([0.7, -1.3])
        assert kabsch_rmsd(p, q) < 1e-12
        assert unregistered_rmsd(p, q) > 0.1
        r, t = kabsch_transform(p, q)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(q @ r.T + t, p, atol=1e-12)


def test_known_noise_after_rigid_motion():
    # Centred, rotation-balanced noise: the optimum stays at the true rotation, RMSD = noise RMS.
    p = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    noise = np.array([[0.01, 0.0], [-0.01, 0.0], [0.01, 0.0], [-0.01, 0.0]])
    q = (p + noise) @ rot(1.1).T + 3.0
    assert kabsch_rmsd(p, q) == pytest.approx(brute_force_rmsd(p, q), abs=1e-10)
    assert kabsch_rmsd(p, q) <= 0.01 + 1e-12


def test_mirrored_arrangement_is_not_aligned_by_a_reflection():
    p = np.array([[0.1, 0.1], [0.8, 0.2], [0.3, 0.7], [0.5, 0.45], [0.9, 0.9]])
    q = p * np.array([-1.0, 1.0]) + 0.5  # mirror image
    assert svd_kabsch_rmsd(p, q, reflections=True) < 1e-12  # a reflection would fit it exactly
    ours = kabsch_rmsd(p, q)
    assert ours > 0.05
    assert ours == pytest.approx(brute_force_rmsd(p, q), abs=1e-9)
    # align_vectors on z = 0 points takes the reflection (a 180-degree in-plane flip): not a reference here.
    p3, q3 = [np.c_[a - a.mean(0), np.zeros(len(a))] for a in (p, q)]
    _, rssd = Rotation.align_vectors(p3, q3)
    assert rssd / np.sqrt(len(p)) < 1e-9 < ours


def test_align_vectors_agrees_where_no_reflection_fits_better():
    rng = np.random.default_rng(2)
    checked = 0
    for _ in range(40):
        p = rng.random((5, 2))
        q = p @ rot(rng.uniform(0, 2 * np.pi)).T + rng.normal(0, 0.05, (5, 2))
        ours = kabsch_rmsd(p, q)
        mirrored_best = brute_force_rmsd(p, q * np.array([-1.0, 1.0]))
        p3, q3 = [np.c_[a - a.mean(0), np.zeros(len(a))] for a in (p, q)]
        _, rssd = Rotation.align_vectors(p3, q3)
        ref = rssd / np.sqrt(len(p))
        assert ours >= ref - 1e-9  # align_vectors may only do better, by reflecting
        if mirrored_best > ours + 1e-3:
            assert ours == pytest.approx(ref, abs=1e-7)
            checked += 1
    assert checked > 30


def test_degenerate_sizes():
    assert np.isnan(kabsch_rmsd(np.zeros((0, 2)), np.zeros((0, 2))))
    assert np.isnan(unregistered_rmsd(np.zeros((0, 2)), np.zeros((0, 2))))
    assert kabsch_rmsd([[0.2, 0.3]], [[0.9, 0.1]]) == 0.0
    # N = 2: only the two distances differ after alignment: RMSD = | |dp| - |dq| | / 2.
    p = np.array([[0.0, 0.0], [0.3, 0.4]])  # length 0.5
    q = np.array([[1.0, 1.0], [1.0, 1.2]])  # length 0.2
    assert kabsch_rmsd(p, q) == pytest.approx(0.15, abs=1e-12)


def test_collinear_and_coincident_points():
    rng = np.random.default_rng(3)
    for _ in range(10):
        t = rng.random(5)
        p = np.c_[t, 2 * t + 0.1]  # on a line
        q = np.c_[rng.random(5), np.full(5, 0.4)]  # on another line
        assert kabsch_rmsd(p, q) == pytest.approx(brute_force_rmsd(p, q), abs=1e-9)
    p = np.full((4, 2), 0.5)  # all at one point: RMSD = spread of the prediction about its centroid
    q = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert kabsch_rmsd(p, q) == pytest.approx(np.sqrt(0.5), abs=1e-12)


def test_batch_equals_single_and_shape_errors():
    rng = np.random.default_rng(4)
    p, q = rng.random((7, 4, 2)), rng.random((7, 4, 2))
    batch = kabsch_rmsd_batch(p, q)
    assert batch == pytest.approx([kabsch_rmsd(a, b) for a, b in zip(p, q)], abs=1e-15)
    assert np.isnan(kabsch_rmsd_batch(np.zeros((3, 0, 2)), np.zeros((3, 0, 2)))).all()
    with pytest.raises(ValueError):
        kabsch_rmsd(np.zeros((3, 2)), np.zeros((2, 2)))


def test_unregistered_rmsd_by_hand():
    p = np.array([[0.0, 0.0], [1.0, 0.0]])
    q = np.array([[0.0, 0.3], [1.0, -0.4]])
    assert unregistered_rmsd(p, q) == pytest.approx(np.sqrt((0.09 + 0.16) / 2))
