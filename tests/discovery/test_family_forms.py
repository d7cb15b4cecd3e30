"""The discovery model carries the chosen member of a spectrum-level family into later rounds."""

from __future__ import annotations

import pytest

from bayes_tfcrds.discovery.views import effect_with_form
from bayes_tfcrds.discovery.workflow import ExperimentModel


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
