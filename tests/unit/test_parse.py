"""The answer parser on a corpus of good and bad answers. It must never raise."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ppprops.wire.parse import final_text, parse_answer, read_answer

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
    # lists without brackets, in the layouts instruction-tuned chat models write
    ("Here are the parameters:\n- 1\n- -2\n- 3.5\n- 4\n\nThey should balance it.", (1, -2, 3.5, 4)),
    ("1. 1\n2. -2\n3. 3.5\n4. 4", (1, -2, 3.5, 4)),
    ("1\n-2\n3.5\n4", (1, -2, 3.5, 4)),
    ("| index | value |\n|---|---|\n| 0 | 1 |\n| 1 | -2 |\n| 2 | 3.5 |\n| 3 | 4 |", (1, -2, 3.5, 4)),
    ("- **theta_0**: 1\n- **theta_1**: -2\n- theta_2: 3.5\n- theta_3 = 4", (1, -2, 3.5, 4)),
    ("W[0][0] = 1\nW[0][1] = -2\nb[0] = 3.5\nb[1] = 4", (1, -2, 3.5, 4)),
    ("1, -2, 3.5, 4", (1, -2, 3.5, 4)),
]
BAD = [
    ("", "empty"),
    (None, "empty"),
    ("   \n ", "empty"),
    ("<think>I should propose something</think>", "reasoning_only"),
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
    ("1. Push left harder.\n2. Keep the rest.", "no_numbers"),  # a numbered list of words holds no vector
]

# A list of the wrong size is wrong_length in every layout (a bullet list of 4 of 10 numbers
# was classified no_numbers, "no parameter vector was found"). D = 10 here; each holds 4 numbers.
SHORT_LISTS = {
    "bullets": "Here is my proposal:\n- 0.5\n- -1.2\n- 3.0\n- 0.1\n\nThis should keep the pole up.",
    "star bullets": "* 0.5\n* -1.2\n* 3.0\n* 0.1",
    "labelled bullets": "- cart position weight: 0.5\n- cart velocity weight: -1.2\n- pole angle: 3.0\n- bias: 0.1",
    "numbered lines": "1. 0.5\n2. -1.2\n3. 3.0\n4. 0.1",
    "numbered with parentheses": "1) 0.5\n2) -1.2\n3) 3.0\n4) 0.1",
    "one per line": "0.5\n-1.2\n3.0\n0.1",
    "one per line with commas": "0.5,\n-1.2,\n3.0,\n0.1",
    "labelled lines": "p0 = 0.5\np1 = -1.2\np2 = 3.0\np3 = 0.1",
    "matrix entries": "W[0][0] = 0.5\nW[0][1] = -1.2\nW[1][0] = 3.0\nb[0] = 0.1",
    "table": "| i | value |\n|---|------|\n| 0 | 0.5 |\n| 1 | -1.2 |\n| 2 | 3.0 |\n| 3 | 0.1 |",
    "one line": "My proposal: 0.5, -1.2, 3.0, 0.1",
    "one line, spaces": "0.5 -1.2 3.0 0.1",
}


@pytest.mark.parametrize("layout", sorted(SHORT_LISTS))
def test_a_short_list_is_wrong_length_in_any_layout(layout: str) -> None:
    r = parse_answer(SHORT_LISTS[layout], 10)
    assert (r.error, r.detail) == ("wrong_length", "expected 10 numbers, got 4"), r


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


# -- where the proposal comes from (the rule in ppprops.wire.parse) ------------------------------------
H = "[9,9,9,9]"  # a quoted history entry, as the list form prints it
READS = [  # (content, reasoning field, finish_reason) -> values, source
    ('params[0]: 9, params[1]: 9, params[2]: 9, params[3]: 9\n{"params": [1, 2, 3, 4]}', None, "stop", (1, 2, 3, 4), "content"),
    (f'best {H}, draft {{"params": [5, 5, 5, 5]}}\n</think>\n{{"params": [1, 2, 3, 4]}}', None, "stop", (1, 2, 3, 4), "content"),
    (f'<think>best {H} {{"params": [5, 5, 5, 5]}}</think>{{"params": [1, 2, 3, 4]}}', None, "stop", (1, 2, 3, 4), "content"),
    (f'<|channel|>analysis<|message|>best {H} {{"params": [5, 5, 5, 5]}}<|end|><|start|>assistant<|channel|>final'
     f'<|message|>{{"params": [1, 2, 3, 4]}}<|return|>', None, "stop", (1, 2, 3, 4), "content"),
    (f'<|channel|>analysis<|message|>best {H}<|end|>{{"params": [1, 2, 3, 4]}}', None, "stop", (1, 2, 3, 4), "content"),
    (f'analysis best {H} {{"params": [5, 5, 5, 5]}} assistantfinal{{"params": [1, 2, 3, 4]}}', None, None, (1, 2, 3, 4), "content"),
    (None, f'best {H}, draft {{"params": [5, 5, 5, 5]}}, final: {{"params": [1, 2, 3, 4]}}', "stop", (1, 2, 3, 4), "reasoning"),
    ("", f"best {H}. My answer: [1, 2, 3, 4]", "stop", (1, 2, 3, 4), "reasoning"),
    ('{"params": [1.5, \u22122.25, \u20133, 4]}', None, "stop", (1.5, -2.25, -3, 4), "content"),
    ('{"params": [1, 2, 3, 4]}', f"best {H}", "stop", (1, 2, 3, 4), "content"),  # content first, whatever the reasoning
]
READ_FAILURES = [
    (None, f'best {H}, so {{"params": [1, 2, 3, 4]}}', "length", "length"),  # cut off: never used
    ('{"params": [1, 2, 3, 4]}', None, "length", "length"),
    (None, f"The best so far is {H}. Let me vary a few.", "stop", "reasoning_only"),  # a quoted list is no answer
    (f"<think>The best so far is {H}", None, "length", "length"),
    (f"<think>The best so far is {H}", None, "stop", "reasoning_only"),
    (f'<|channel|>analysis<|message|>best {H}<|end|>', None, "stop", "reasoning_only"),
    (None, None, "stop", "empty"),
    ('{"params": [1, 2, 3, 4]}', None, "content_filter", "refusal"),
    ('{"params": [1, 2, 3, 4]} and {"params": [4, 3, 2, 1]}', None, "stop", "several_vectors"),
]


@pytest.mark.parametrize("content,reasoning,finish,values,source", READS)
def test_the_answer_comes_from_the_final_content_first(content, reasoning, finish, values, source) -> None:  # type: ignore[no-untyped-def]
    r = read_answer(content, reasoning, D, finish_reason=finish)
    assert r.ok, r
    assert r.values == pytest.approx(values) and r.source == source


@pytest.mark.parametrize("content,reasoning,finish,kind", READ_FAILURES)
def test_reasoning_and_cut_off_answers_are_never_the_source(content, reasoning, finish, kind) -> None:  # type: ignore[no-untyped-def]
    r = read_answer(content, reasoning, D, finish_reason=finish)
    assert not r.ok and r.error == kind, r
    assert "<|" not in r.detail and "HTTP" not in r.detail


MARKUP = st.sampled_from(["<|channel|>analysis<|message|>", "<|end|>", "<|start|>assistant", "<|channel|>final<|message|>",
                          "<think>", "</think>", "<thinking>", "</reasoning>", "<|return|>", "<|channel|>commentary to=x<|constrain|>json<|message|>"])


@given(st.lists(st.one_of(MARKUP, st.text(alphabet="abc {}[]0123456789,.:-\n", max_size=20)), max_size=12))
def test_final_text_never_carries_markup(parts: list[str]) -> None:
    text = final_text("".join(parts))
    assert not re.search(r"<\|[a-z_]+\|>", text) and not re.search(r"</?(think|thinking|reasoning|thought)>", text)
