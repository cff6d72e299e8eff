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


def _numbers(schema: dict) -> list[dict]:
    """The number schemas of a field: itself, or its array's items."""
    if schema.get("type") == "array":
        return _numbers(schema["items"])
    return [schema] if schema.get("type") in ("integer", "number") else []


@pytest.mark.parametrize("name", sorted(BakeSettings.model_fields))
def test_every_number_is_bounded(name):
    """Every numeric field (list entries included) has a lower and an upper bound."""
    prop = BakeSettings.model_json_schema()["properties"][name]
    for num in _numbers(prop):
        assert {"minimum", "exclusiveMinimum"} & set(num), (name, num)
        assert {"maximum", "exclusiveMaximum"} & set(num), (name, num)


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan"), 2e6])
def test_non_finite_or_huge_switch_sizes_are_refused(value):
    with pytest.raises(ValueError, match="lod_switch_px"):
        BakeSettings(lod_switch_px=(value,))
    with pytest.raises(ValueError, match="lod_switch_px"):
        BakeSettings.model_validate_json('{"lod_switch_px": [Infinity]}')


def test_valid_settings_read_back_from_their_json():
    """Whatever validates reads back from its JSON (what the job database stores), equal."""
    import random

    rng = random.Random(7)
    for _ in range(50):
        px = sorted((rng.uniform(1e-3, 1e6) for _ in range(rng.randint(1, 8))), reverse=True)
        s = BakeSettings(lod_switch_px=tuple(px), seed=rng.randint(0, 2**32 - 1),
                         eps_db=rng.uniform(1e-9, 200.0), warp=rng.choice(["", "bend:angle=90"]))
        assert BakeSettings.model_validate_json(s.model_dump_json()) == s


def test_readme_lists_every_field_in_its_group():
    """The README's "Bake settings" table is the schema's grouping, field for field."""
    import re
    from pathlib import Path

    from schemas.settings import GROUPS

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    table = text.split("## Bake settings", 1)[1].split("\n## ", 1)[0]
    rows = dict(re.findall(r"^\| ([a-z_ ]+) \| (.+) \|$", table, re.M))
    listed = {g: re.findall(r"`(\w+)`", rows.get(g, "")) for g in GROUPS}
    want = {g: [n for n, f in BakeSettings.model_fields.items()
                if f.json_schema_extra["group"] == g] for g in GROUPS}
    assert listed == want


def test_bake_help_lists_every_field_by_group():
    """`texelbake bake --help` ends with every setting and its default, under its group."""
    from texelbake.cli import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices["bake"]
    text = sub.format_help()
    for group in GROUPS:
        assert f"  {group}: " in text
    for name in BakeSettings.model_fields:
        assert f"{name}=" in text
