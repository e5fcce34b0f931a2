"""The adaptive controller: the paper's rule, exactly, and the schedule scaling."""

from __future__ import annotations

import pytest

from pipeline.water import (
    ControllerConfig,
    ControllerSettings,
    WaterDecision,
    controller_settings,
    medium_start_iteration,
    water_index,
)


@pytest.mark.parametrize(
    "water_type, lr_att, lr_scat, alpha, beta",
    [
        ("clear", 2.5e-4, 5e-5, 1.2, 0.8),  # both base rates halved: scattering 1e-4 → 5e-5 as printed
        ("medium", 5e-4, 1e-4, 1.0, 1.0),  # the base rates, neutral weights
        ("turbid", 5e-4, 1e-4, 0.8, 1.2),  # rates "maintained"
    ],
)
def test_paper_rule(water_type, lr_att, lr_scat, alpha, beta):
    s = controller_settings(water_type)
    assert (s.water_type, s.alpha, s.beta) == (water_type, alpha, beta)
    assert s.lr_attenuation == pytest.approx(lr_att, rel=1e-12)
    assert s.lr_scattering == pytest.approx(lr_scat, rel=1e-12)
    assert s.medium_start_fraction == pytest.approx(1 / 3)
    assert s.medium_start(30_000) == 10_000


def test_literal_reading_is_one_config_change_away():
    # "reduced from 1e-4 to 5e-5" read as absolute values for both models: factor 0.1 on 5e-4 and 0.5 on 1e-4
    # cannot be one factor, so the literal reading sets explicit base rates instead.
    cfg = ControllerConfig(lr_attenuation=1e-4, lr_scattering=1e-4)
    s = controller_settings("clear", cfg)
    assert (s.lr_attenuation, s.lr_scattering) == (pytest.approx(5e-5), pytest.approx(5e-5))


def test_unknown_water_type():
    with pytest.raises(ValueError, match="unknown water type"):
        controller_settings("murky")


@pytest.mark.parametrize("total, start", [(30_000, 10_000), (3_000, 1_000), (7_000, 2_333), (100, 33), (2, 1),
                                          (1, 0), (0, 0)])
def test_schedule_scaling(total, start):
    assert medium_start_iteration(total) == start


def test_schedule_custom_fraction_and_errors():
    assert medium_start_iteration(1000, 0.5) == 500
    assert medium_start_iteration(1000, 1.0) == 1000
    with pytest.raises(ValueError):
        medium_start_iteration(-1)
    with pytest.raises(ValueError):
        medium_start_iteration(100, 1.5)


def test_water_index_mapping():
    assert water_index(1.0) == pytest.approx(0.5)
    assert water_index(2.0) == 1.0 and water_index(5.0) == 1.0
    assert water_index(0.5) == 0.0 and water_index(0.1) == 0.0
    assert water_index(2**0.5) == pytest.approx(0.75)  # log-linear between the ends
    with pytest.raises(ValueError):
        water_index(0.0)


def test_decision_to_dict_is_flat_and_complete():
    s = controller_settings("turbid")
    d = WaterDecision("turbid", {"clear": 0.1, "medium": 0.2, "turbid": 0.7}, 0.4, 0.87, 3, s).to_dict()
    assert d == {"water_type": "turbid", "probabilities": {"clear": 0.1, "medium": 0.2, "turbid": 0.7},
                 "closest": "turbid", "known": True, "confidence": 1.0, "reason": None, "ood": None,
                 "settings_from": "turbid", "index_w": 0.4, "bg_ratio": 0.87, "n_images": 3,
                 "lr_attenuation": 5e-4, "lr_scattering": 1e-4,
                 "alpha": 0.8, "beta": 1.2, "medium_start_fraction": pytest.approx(1 / 3),
                 "init_optical_depth": (1.5, 0.9, 1.0)}
    assert isinstance(s, ControllerSettings) and s.to_dict()["water_type"] == "turbid"
