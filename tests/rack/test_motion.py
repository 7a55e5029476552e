"""Motion fields of the generators and of the gaps against numeric differences of the projection."""

from __future__ import annotations

import numpy as np
import pytest

from companion.camera import PinholeCamera
from companion.geometry import se3, so3
from companion.vision.rack import RackModel
from companion.vision.rack.limbs import sample_limbs
from companion.vision.rack.motion import (
    gap_jacobian,
    gravity_rows,
    median_1d,
    pose_jacobian,
    robust_weights,
    solve_normal_equations,
    strength_weights,
)
from tests.numdiff import central_jacobian

CAM = PinholeCamera(width=720, height=480, fx=630.0, fy=630.0, cx=360.0, cy=240.0)
R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _pose(rng: np.random.Generator) -> np.ndarray:
    R = so3.exp(rng.normal(0, 0.1, 3)) @ R_DOWN
    return se3.make(R, [0.6 + rng.normal(0, 0.1), 4.0 + rng.normal(0, 0.3), 2.4 + rng.normal(0, 0.2)])


def test_point_motion_fields_match_central_differences(rng: np.random.Generator) -> None:
    T = _pose(rng)
    p_rack = np.array([[0.3, 4.2, 0.1], [1.0, 3.5, 0.3], [0.5, 4.8, 0.0]])

    def project(delta: np.ndarray) -> np.ndarray:
        Tp = T @ se3.exp(delta)
        return CAM.project(se3.act(se3.inverse(Tp), p_rack)).ravel()

    p_cam = se3.act(se3.inverse(T), p_rack)
    _, J = CAM.project_with_jacobian(p_cam)
    analytic = pose_jacobian(J, p_cam).reshape(-1, 6)
    np.testing.assert_allclose(analytic, central_jacobian(project, np.zeros(6)), rtol=1e-5, atol=1e-4)


def test_gap_motion_field_matches_central_differences(rng: np.random.Generator) -> None:
    T = _pose(rng)
    p_rack = np.array([[0.9, 4.2, 0.1], [1.3, 3.5, 0.3]])

    def project(dx: np.ndarray) -> np.ndarray:
        return CAM.project(se3.act(se3.inverse(T), p_rack + np.array([dx[0], 0.0, 0.0]))).ravel()

    p_cam = se3.act(se3.inverse(T), p_rack)
    _, J = CAM.project_with_jacobian(p_cam)
    analytic = gap_jacobian(J, T[:3, :3].T).reshape(-1, 1)
    np.testing.assert_allclose(analytic, central_jacobian(project, np.zeros(1)), rtol=1e-5, atol=1e-4)


def _signed_distance_to_limbs(T: np.ndarray, model: RackModel, uv: np.ndarray, n: np.ndarray,
                              limb: np.ndarray, gaps: np.ndarray | None = None) -> np.ndarray:
    """Signed distance along n from uv to the limb line re-rendered at pose T (per sample)."""
    s = sample_limbs(T, CAM, model.pipe_arrays(gaps), 8, occlusion_margin_px=0.0)
    out = np.empty(uv.shape[0])
    for i in range(uv.shape[0]):
        pts = s.uv[s.limb == limb[i]]
        a, b = pts[0], pts[-1]
        t = (b - a) / np.linalg.norm(b - a)
        # Intersection of the ray uv + k n with the line a + s t.
        M = np.column_stack([n[i], -t])
        k, _ = np.linalg.solve(M, a - uv[i])
        out[i] = k
    return out


def test_limb_normal_motion_matches_rerendered_limbs(rng: np.random.Generator) -> None:
    """σ = ξᵀ n of limb points equals the numeric derivative of the re-rendered limb's distance."""
    model = RackModel.parallel(radii=[0.15, 0.2, 0.15], gaps=[0.1, 0.12], length=10.0)
    T = _pose(rng)
    s = sample_limbs(T, CAM, model.pipe_arrays(), 8)
    pick = np.arange(0, s.uv.shape[0], 5)
    uv, n, limb = s.uv[pick], s.normal_px[pick], s.limb[pick]
    sigma = np.einsum("nij,ni->nj", pose_jacobian(s.J_uv_pcam[pick], s.p_cam[pick]), n)

    def dist(delta: np.ndarray) -> np.ndarray:
        return _signed_distance_to_limbs(T @ se3.exp(delta), model, uv, n, limb)

    numeric = central_jacobian(dist, np.zeros(6), eps=1e-6)
    np.testing.assert_allclose(sigma, numeric, rtol=1e-3, atol=2e-2)
    # Gap parameters: cumulative gap k moves pipe k+1.
    gaps0 = model.cumulative_gaps
    gap_cols = np.zeros((pick.size, gaps0.size))
    gi = model.pipe_arrays().gap_index[s.pipe[pick]]
    g = np.einsum("ni,ni->n", gap_jacobian(s.J_uv_pcam[pick], T[:3, :3].T), n)
    for j in range(pick.size):
        if gi[j] >= 0:
            gap_cols[j, gi[j]] = g[j]

    def dist_g(dg: np.ndarray) -> np.ndarray:
        return _signed_distance_to_limbs(T, model, uv, n, limb, gaps0 + dg)

    np.testing.assert_allclose(gap_cols, central_jacobian(dist_g, np.zeros(gaps0.size), eps=1e-6),
                               rtol=1e-3, atol=2e-2)


def test_irls_recovers_parameters_despite_outliers(rng: np.random.Generator) -> None:
    A = rng.normal(size=(300, 6)) * 100.0
    x_true = rng.normal(size=6) * 0.01
    r = A @ x_true + rng.normal(0, 0.2, 300)
    r[:30] += rng.uniform(20, 40, 30)  # 10 % gross outliers
    x = np.zeros(6)
    for kind, gate in (("paper", 4.0), ("tukey", None)):
        x = np.zeros(6)
        for _ in range(10):
            w = robust_weights(r - A @ x, kind, 1.0, gate_px=gate)
            dx, _, _ = solve_normal_equations(A, r - A @ x, w, np.full(6, 1e-6))
            x = x + dx
        np.testing.assert_allclose(x, x_true, atol=2e-4)
    w = robust_weights(np.array([0.0, 1.0, 10.0]), "paper", 1.0, gate_px=5.0)
    np.testing.assert_allclose(w, [1.0, 0.5, 0.0])


def test_tukey_weights_ignore_a_one_sided_cluster_inside_the_gate(rng: np.random.Generator) -> None:
    """15 % of the rows 2-3.5 px off on one side (a ground edge beside a limb, inside the 4 px gate): the
    paper's weights 1/(1 + |e|) keep a third of their weight and bias the offset by ~0.2 px; Tukey's
    biweight (c = 4.685 x the MAD scale, ~1.9 px here) gives them none."""
    bias = {"paper": [], "tukey": []}
    for _ in range(40):
        A = np.column_stack([np.ones(300), rng.normal(size=(300, 2))])
        r = rng.normal(0.0, 0.4, 300)
        r[:45] = rng.uniform(2.0, 3.5, 45)
        for kind in bias:
            x = np.zeros(3)
            for _ in range(5):
                w = robust_weights(r - A @ x, kind, 1.0, gate_px=4.0)
                dx, _, _ = solve_normal_equations(A, r - A @ x, w, np.full(3, 1e-6))
                x = x + dx
            bias[kind].append(x[0])
    assert np.mean(bias["paper"]) > 0.15
    assert abs(np.mean(bias["tukey"])) < 0.02


def test_median_1d_matches_numpy(rng: np.random.Generator) -> None:
    for n in [*range(1, 12), 101, 384]:
        for scale in (1e-3, 1.0, 1e5):
            a = rng.normal(0.0, scale, n)
            assert median_1d(a) == float(np.median(a))
    assert median_1d(np.array([2.0, 2.0, 1.0, 1.0])) == 1.5
    assert np.isnan(median_1d(np.array([1.0, np.nan, 2.0])))


def test_gravity_rows_match_central_differences(rng: np.random.Generator) -> None:
    T = _pose(rng)
    R_prior = so3.exp(rng.normal(0, 0.01, 3)) @ T[:3, :3]

    def residual(delta: np.ndarray) -> np.ndarray:
        return gravity_rows((T @ se3.exp(delta))[:3, :3], R_prior)[0]

    r0, A = gravity_rows(T[:3, :3], R_prior)
    # r(δ) ≈ r0 - A δ: the rows predict the residual's change (r = g_p - g, dg/dδ = A).
    np.testing.assert_allclose(-A, central_jacobian(residual, np.zeros(6)), atol=1e-7)
    # A heading-only difference leaves the residual at zero; a tilt does not.
    yawed = so3.exp([0.0, 0.0, 0.3]) @ T[:3, :3]
    assert np.abs(gravity_rows(T[:3, :3], yawed)[0]).max() < 1e-12
    assert np.linalg.norm(r0) > 1e-3


def test_gated_residual_variance_counts_only_rows_inside_the_gate_with_weight() -> None:
    from companion.vision.rack.motion import gated_residual_variance

    w = np.array([1.0, 0.5, 0.0, 1.0, 2.0])
    r_gate = np.array([0.5, -1.0, 0.2, 9.0, 2.0])  # row 3 outside a 3 px gate, row 2 without weight
    r = np.array([0.4, -0.8, 5.0, 7.0, 1.0])
    expected = (1.0 * 0.16 + 0.5 * 0.64 + 2.0 * 1.0) / (3 - 1)
    assert gated_residual_variance(w, r_gate, r, 3.0, 1) == pytest.approx(expected)
    assert gated_residual_variance(w, r_gate, r, 3.0, 6) == pytest.approx(expected * 2)  # at least one dof


def test_strength_weights_scale_edge_rows_by_their_contrast_relative_to_the_median() -> None:
    """(strength / median) ** power, clipped: a limb at a quarter of the median contrast counts 0.71 at power 0.25,
    one at four times 1.41; the clip keeps a lone strong edge (or a near-zero one) from deciding alone."""
    s = np.array([10.0, 40.0, 40.0, 40.0, 160.0])  # median 40
    np.testing.assert_allclose(strength_weights(s, 0.25), [0.25**0.25, 1.0, 1.0, 1.0, 4.0**0.25])
    np.testing.assert_allclose(strength_weights(s, 2.0), [0.0625, 1.0, 1.0, 1.0, 4.0])  # 16 clipped to 4
    np.testing.assert_allclose(strength_weights(np.array([0.001, 40.0, 40.0]), 1.0), [0.05, 1.0, 1.0])  # floor
    np.testing.assert_array_equal(strength_weights(s, 0.0), np.ones(5))  # off
    assert strength_weights(np.zeros(0), 0.25).shape == (0,)


def test_a_capped_biweight_scale_drops_a_coherent_half_of_outliers() -> None:
    """Half the residuals on a wrong edge 3 px out: the MAD scale is ~2.3 px and the biweight keeps them (weight
    ~0.8); with the scale capped at 0.8 px (c = 3.7 px) they get ~0.1, and the inliers keep theirs."""
    rng = np.random.default_rng(11)
    r = np.concatenate([0.3 * rng.standard_normal(50), 3.0 + 0.3 * rng.standard_normal(50)])
    free = robust_weights(r, "tukey", 1.0, gate_px=4.0)
    capped = robust_weights(r, "tukey", 1.0, gate_px=4.0, max_scale_px=0.8)
    assert np.median(free[50:]) > 0.7
    assert np.median(capped[50:]) < 0.15
    assert np.median(capped[:50]) > 0.9
    # a cap above the MAD scale changes nothing
    assert np.array_equal(robust_weights(r, "tukey", 1.0, 4.0, max_scale_px=50.0), free)
