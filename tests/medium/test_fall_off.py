"""Whether the restore stage divides the survey's in-frame fall-off out of the photos."""

import numpy as np

from pipeline.medium.exposure_gains import field_span
from pipeline.medium.fall_off import MIN_SPAN, fall_off_to_remove


def test_a_measured_fall_off_is_removed_and_noise_or_none_is_not():
    strong = np.array([0.0, -0.2, -0.3, -0.2, 0.0])
    weak = np.array([0.01, 0.0, -0.01, 0.0, 0.0])
    assert field_span(strong) > 1.5 and field_span(weak) < MIN_SPAN
    got = fall_off_to_remove({"exposure_field": strong.tolist(), "field_span": field_span(strong)})
    assert got.record["removed"] and np.allclose(got.log_field, strong)
    for est in ({"exposure_field": weak.tolist(), "field_span": field_span(weak)}, {}, None,
                {"exposure_field": None, "field_span": None}):
        got = fall_off_to_remove(est)
        assert got.log_field is None and not got.record["removed"] and got.record["reason"]


def test_the_removed_field_keeps_the_photos_mean_exposure():
    """Divided out at its shape, not its level: a mean of 1 over the frame in linear light (a 4x lamp's cone,
    1 at the centre, would otherwise brighten every photo by its mean); the shape is the fit's."""
    from pipeline.medium.exposure_gains import field_map
    from pipeline.medium.fall_off import field_level, log_fall_off_map

    theta = np.array([0.2, -0.5, -0.6, -0.5, 0.1])
    m = log_fall_off_map(400, 300, theta)
    assert abs(np.mean(np.exp(m)) - 1) < 0.01 and field_level(theta) < -0.2
    np.testing.assert_allclose(m - m.mean(), field_map(400, 300, theta) - field_map(400, 300, theta).mean(), atol=1e-9)
