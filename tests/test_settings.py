"""BakeSettings as the user reads it: every field in one of GROUPS, described in one sentence."""

from __future__ import annotations

import re

import pytest

from schemas.settings import GROUPS, BakeSettings


def test_every_field_names_its_group_in_the_schema():
    props = BakeSettings.model_json_schema()["properties"]
    assert set(props) == set(BakeSettings.model_fields)
    assert {p["group"] for p in props.values()} == set(GROUPS)
    # fields are declared group by group, in GROUPS' order
    order = [GROUPS.index(p["group"]) for p in props.values()]
    assert order == sorted(order)


@pytest.mark.parametrize("name", sorted(BakeSettings.model_fields))
def test_a_description_is_one_sentence_without_tickets_or_dates(name):
    text = BakeSettings.model_fields[name].description
    assert text and text.lstrip("'")[0].isalpha() and text.endswith("."), name
    assert not re.search(r"(?<!Eq)\. ", text), f"{name}: more than one sentence: {text!r}"
    assert not re.search(r"issue \d|\d{4}-\d{2}-\d{2}|\d\s*(dB|%|×)", text), f"{name}: {text!r}"


def test_removed_experiments_are_refused():
    with pytest.raises(ValueError, match="coarse_target"):
        BakeSettings(coarse_target="dense")
