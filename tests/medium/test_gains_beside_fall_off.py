"""Each view's gains beside the in-frame fall-off (pipeline.medium.exposure_gains) on sightings of a towed camera's
line: the points move down the frame by a fixed step from one view to the next, the photos are darker at the
frame's top than at its bottom (as on the AIMS Erub line), and the views' exposure is fixed or changes by ±30 %."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.medium.exposure_gains import (
    FIELD_SIGMA,
    PRIOR_SIGMA,
    field_basis,
    field_span,
    field_values,
    gains_beside_field,
)

THETA = np.array([-0.05, 0.3, -0.1, -0.05, 0.02])  # brighter at the bottom (y = +1), darker towards the sides


def line_sightings(n_views: int, log_gains: np.ndarray, seed: int = 0, noise: float = 0.01,
                   ) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], np.ndarray]:
    """Per channel: log(seen / predicted), view and image position of each sighting of a line survey at constant
    speed (a point enters at the top and moves down 0.35 half-heights a frame), the field THETA on every photo;
    and each view's prior mean (its photo's log mean brightness: the gains, the field's mean and the content's
    variation of ±3 %). ``log_gains`` [V, 3]."""
    rng = np.random.default_rng(seed)
    views, xys = [], []
    for _ in range(900):
        x, y0, k0 = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.integers(0, n_views)
        for k in range(k0, n_views):
            y = y0 + 0.35 * (k - k0)
            if y > 1:
                break
            views.append(k)
            xys.append((x, y))
    view, xy = np.array(views), np.array(xys)
    ratios = [log_gains[view, c] + field_values(xy, THETA)[:, 0] + rng.normal(0, noise, len(view)) for c in range(3)]
    prior = log_gains + rng.normal(0, 0.03, log_gains.shape)
    return ratios, [view] * 3, [xy] * 3, prior - prior.mean(0)


def test_a_fixed_camera_under_a_fall_off_keeps_its_exposure():
    """The field takes the fall-off (the whole fit's chained case, where each point's colour comes from its own
    sightings, is in test_exposure_fit)."""
    n = 20
    ratios, views, xys, prior = line_sightings(n, np.zeros((n, 3)))
    lg, se, theta = gains_beside_field(ratios, views, xys, n, prior)
    lg -= lg.mean(0)
    assert np.abs(np.expm1(lg)).max() < 0.02, np.abs(np.expm1(lg)).max()
    np.testing.assert_allclose(theta, THETA, atol=0.02)
    assert field_span(theta) == pytest.approx(field_span(THETA), rel=0.03)


def test_changing_exposure_is_recovered_beside_the_fall_off():
    n = 20
    rng = np.random.default_rng(1)
    truth = np.log(rng.uniform(0.7, 1.3, (n, 1)) * rng.uniform(0.9, 1.1, (n, 3)))
    truth -= truth.mean(0)
    ratios, views, xys, prior = line_sightings(n, truth, seed=2)
    lg, se, _ = gains_beside_field(ratios, views, xys, n, prior)
    lg -= lg.mean(0)
    assert np.abs(np.expm1(lg - truth)).max() < 0.02
    assert np.isfinite(se).all() and (se < 0.01).all()


def test_matches_a_direct_least_squares():
    """The normal equations assembled by bincount against numpy's least squares on the dense design (one row per
    sighting, one per prior), on noise-free sightings with Gaussian weights (Huber's never bite)."""
    n = 6
    rng = np.random.default_rng(3)
    truth = rng.normal(0, 0.1, (n, 3))
    ratios, views, xys, prior = line_sightings(n, truth, seed=4, noise=0.0)
    lg, _, theta = gains_beside_field(ratios, views, xys, n, prior)
    # the same problem, dense: the rows of each channel at its measured noise (1e-4, the floor), then the priors
    s = 1e-4
    design, target = [], []
    for c in range(3):
        onehot = np.zeros((len(views[c]), 3 * n))
        onehot[np.arange(len(views[c])), c * n + views[c]] = 1
        design.append(np.hstack([onehot, field_basis(xys[c])]) / s)
        target.append(ratios[c] / s)
    design.append(np.hstack([np.eye(3 * n), np.zeros((3 * n, 5))]) / PRIOR_SIGMA)
    target.append(prior.T.reshape(-1) / PRIOR_SIGMA)
    design.append(np.hstack([np.zeros((5, 3 * n)), np.eye(5)]) / FIELD_SIGMA)
    target.append(np.zeros(5))
    sol = np.linalg.lstsq(np.vstack(design), np.concatenate(target), rcond=None)[0]
    np.testing.assert_allclose(lg, sol[:3 * n].reshape(3, n).T, atol=1e-6)
    np.testing.assert_allclose(theta, sol[3 * n:], atol=1e-6)


def test_unseen_views_and_no_positions():
    ratios = [np.array([0.1, 0.12, 0.08])] * 3
    views = [np.array([0, 0, 0])] * 3
    lg, se, theta = gains_beside_field(ratios, views, None, 3)
    assert np.isinf(se[1:]).all() and (lg[1:] == 0).all() and not theta.any()
    assert np.isfinite(se[0]).all() and lg[0, 0] == pytest.approx(0.1, abs=0.01)
