"""The discovery model carries the chosen member of a spectrum-level family into later rounds."""

from __future__ import annotations

import pytest

from bayes_tfcrds.discovery.views import effect_with_form
from bayes_tfcrds.discovery.workflow import (
    Candidate,
    ExperimentModel,
    indistinguishable,
)


def test_spectrum_forms_follow_the_model():
    m = ExperimentModel(frozenset({"etalon"})).plus("neighbour_line", "neighbour_width")
    # a later evaluation fits the line with the member's extra, and plus() keeps it
    assert m.spectrum_extras == ("etalon", "neighbour_line", "neighbour_width")
    assert m.plus("speed_dependence").forms == {"neighbour_width"}
    assert "neighbour_width" in m.label()
    assert ExperimentModel(frozenset({"etalon"})).label() == "crds+voigt+etalon"
    with pytest.raises(ValueError, match="need their effect"):
        ExperimentModel(frozenset({"etalon"}), frozenset({"neighbour_width"}))


def test_report_names_the_member():
    step = {"effect": "extinction_tail", "form": "2 exponentials"}
    assert effect_with_form(step) == "extinction_tail (2 exponentials)"
    assert effect_with_form({"effect": "transfer_function", "form": ""}) == "transfer_function"


def test_line_shape_members_set_the_profile():
    sd = ExperimentModel().plus("speed_dependence", "sd_power_law")
    assert sd.profile == "sdvp_power"
    assert sd.spectrum_extras == ()  # a profile member is not a spectrum extra
    assert "sd_power_law" in sd.label()
    hc = ExperimentModel().plus("hard_collisions", "soft_collisions")
    assert hc.profile == "galatry"
    # both effects: the qSDHCP, and the single-effect members are dropped
    both = sd.plus("hard_collisions")
    assert both.profile == "qsdhcp" and both.forms == frozenset()
    with pytest.raises(ValueError, match="need their effect"):
        ExperimentModel(frozenset({"etalon"}), frozenset({"soft_collisions"}))


def _cand(effect, evidence, block="spectrum"):
    return Candidate(effect, evidence, evidence, 1, 21, block, {}, None, "")


def test_indistinguishable_candidates_are_named_beside_the_added_one():
    best = _cand("speed_dependence", 15403.0)
    passing = [
        best,
        _cand("hard_collisions", 15402.8),  # Delta BIC 0.2: the data cannot tell
        _cand("etalon", 15400.5),  # 2.5 apart: told apart
        _cand("extinction_tail", 15403.1, "transients"),  # another data block
    ]
    alts = indistinguishable(best, passing)
    assert [a["effect"] for a in alts] == ["hard_collisions"]
    assert abs(alts[0]["evidence"] - 15402.8) < 1e-9
    # one tried and rejected (it explained too little of the open misfit) is no alternative
    passing[1].tried, passing[1].explained = True, 0.2
    assert indistinguishable(best, passing) == []
    passing[1].explained = 0.9  # tried and accepted: still one
    assert [a["effect"] for a in indistinguishable(best, passing)] == ["hard_collisions"]
    step = {
        "effect": "speed_dependence",
        "form": "quadratic",
        "alternatives": [{"effect": "hard_collisions", "form": "soft collisions (Galatry)"}],
    }
    assert effect_with_form(step) == (
        "speed_dependence (quadratic) or hard_collisions (soft collisions (Galatry))"
    )
