"""The answer parser on a corpus of good and bad answers. It must never raise."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ppprops.wire.parse import parse_answer

D = 4
GOOD = [
    ('{"params": [1, -2.5, 3e-2, 4]}', (1, -2.5, 0.03, 4)),
    ('{"params":[1,2,3,4]}', (1, 2, 3, 4)),
    ("[1.0, 2.0, 3.0, 4.0]", (1, 2, 3, 4)),
    ("```json\n{\"params\": [1, 2, 3, 4]}\n```", (1, 2, 3, 4)),
    ("<think>try [9, 9, 9, 9] first... no</think>\n{\"params\": [1, 2, 3, 4]}", (1, 2, 3, 4)),
    ("params[0]: 1\nparams[1]: -2\nparams[2]: 3.5E+1\nparams[3]: .5", (1, -2, 35, 0.5)),
    ("params[0] = 1, params[1] = 2, params[2] = 3, params[3] = 4", (1, 2, 3, 4)),
    ("Here is my proposal: {\"params\": [1, 2, 3, 4]} I hope it helps.", (1, 2, 3, 4)),
    ('{"parameters": [1, 2, 3, 4]}', (1, 2, 3, 4)),
    ('{"params": ["1", "2", "3", "4"]}', (1, 2, 3, 4)),
    ('{"params": [1, 2, 3, 4]}\n{"params": [1, 2, 3, 4]}', (1, 2, 3, 4)),  # same vector restated
    ('{"params": [1e6, -1e6, 0, 0]}', (1e6, -1e6, 0, 0)),  # huge but finite: accepted, clipped later
]
BAD = [
    ("", "empty"),
    (None, "empty"),
    ("   \n ", "empty"),
    ("<think>I should propose something</think>", "empty"),
    ("I'm sorry, but I can't help with that.", "refusal"),
    ("The policy should push left more.", "no_numbers"),
    ('{"params": [1, 2, 3]}', "wrong_length"),
    ('{"params": [1, 2, 3, 4, 5]}', "wrong_length"),
    ('{"params": [1, 2, NaN, 4]}', "non_finite"),
    ('{"params": [1, 2, Infinity, 4]}', "non_finite"),
    ("params[0]: 1\nparams[1]: inf\nparams[2]: 3\nparams[3]: 4", "non_finite"),
    ('{"params": [1, 2, 3, 4]} or maybe {"params": [4, 3, 2, 1]}', "several_vectors"),
    ('{"params": [1.5, -2.25, 3', "truncated"),
    ("params[0]: 1\nparams[2]: 3\nparams[3]: 4", "wrong_length"),
]


@pytest.mark.parametrize("text,expected", GOOD)
def test_good_answers(text: str, expected: tuple[float, ...]) -> None:
    r = parse_answer(text, D)
    assert r.ok, r
    assert r.values == pytest.approx(expected)


@pytest.mark.parametrize("text,kind", BAD)
def test_bad_answers_are_typed_failures(text: str | None, kind: str) -> None:
    r = parse_answer(text, D)
    assert not r.ok
    assert r.error == kind, r
    assert r.detail


@given(st.text(max_size=300))
def test_never_raises_on_arbitrary_text(text: str) -> None:
    r = parse_answer(text, D)
    assert r.ok or r.error


@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=32), min_size=D, max_size=D))
def test_round_trips_json_vectors(values: list[float]) -> None:
    import json

    r = parse_answer(json.dumps({"params": values}), D)
    assert r.ok and r.values == pytest.approx(tuple(values))
