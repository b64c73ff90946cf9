"""The Python API's options derive from the settings table: every setting is reachable from
``ppprops.search`` / ``create_study`` in exactly one place, and every key those take names a setting."""

from __future__ import annotations

import inspect
from typing import get_type_hints

import pytest

import ppprops
from ppprops.api import StudyOptions, _build, _group_values
from ppprops.errors import ConfigError
from ppprops.settings import API_GROUPS, SETTINGS, api_groups

# Settings that are not options of a study: the task argument names the task.
TASK_ARGUMENT = {"env", "task_file"}


def test_every_setting_is_an_option_of_search_and_create_study_exactly_once() -> None:
    groups = api_groups()
    keywords = set(get_type_hints(StudyOptions)) - set(API_GROUPS) - {"method_options"}
    assert set(API_GROUPS) <= set(get_type_hints(StudyOptions))  # every group is an option
    for s in SETTINGS:
        places = [g for g, keys in groups.items() if keys.get(s.api_name) is s] + (["keyword"] if s.api_group is None and s.api_name in keywords else [])
        if s.key in TASK_ARGUMENT:
            assert places == [], s.key
        elif s.key == "method_options":
            assert places == [] and "method_options" in get_type_hints(StudyOptions)
        else:
            assert len(places) == 1, (s.key, places)
    for name in keywords:  # every keyword of its own is a setting of that name (its api_name: --init-policy's is init_policies)
        assert any(s.api_name == name and s.api_group is None for s in SETTINGS), name


def test_search_and_create_study_take_the_same_options() -> None:
    for fn in (ppprops.search, ppprops.create_study):
        kinds = {p.name: p.kind for p in inspect.signature(fn).parameters.values()}
        assert kinds["options"] is inspect.Parameter.VAR_KEYWORD


@pytest.mark.parametrize("group,key,setting", [("prompt", "form", "prompt_form"), ("prompt", "digits", "param_digits"),
                                               ("evaluation", "select_top", "select_top"), ("llm", "timeout", "timeout"),
                                               ("llm", "on_llm_failure", "on_llm_failure"), ("task_options", "obs_keys", "obs_keys"),
                                               ("task_options", "components", "component")])
def test_a_group_key_becomes_its_setting(group: str, key: str, setting: str) -> None:
    assert _group_values(group, {key: 1}) == {setting: 1}


def test_an_llm_config_object_gives_its_settings() -> None:
    from ppprops.llm.settings import LLMConfig

    values = _group_values("llm", LLMConfig(base_url="http://h/v1", model="m", timeout_s=12.0, transport_retries=2))
    assert values["timeout"] == 12.0 and values["retries"] == 2 and values["base_url"] == "http://h/v1"


def test_an_unknown_group_key_names_the_closest_one() -> None:
    with pytest.raises(ConfigError, match=r"^prompt: unknown option 'fomr' \(did you mean form\?\)$"):
        _group_values("prompt", {"fomr": "chat"})


def test_an_unknown_option_is_one_line_naming_the_closest_one() -> None:
    with pytest.raises(ConfigError, match=r"^unknown option 'iteratoins' \(did you mean iterations\?\)$"):
        _build("CartPole", {"iteratoins": 3})  # type: ignore[typeddict-unknown-key]
    with pytest.raises(ConfigError, match=r"^unknown option 'outt' \(did you mean out\?\)$"):
        ppprops.search("CartPole", outt="x")  # type: ignore[call-arg]
    with pytest.raises(ConfigError, match=r"^unknown option 'zzz' \(known: method, warmup, .*, task_options, storage\)$"):
        ppprops.create_study("CartPole", zzz=1)  # type: ignore[call-arg]
