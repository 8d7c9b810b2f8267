"""research/study_config.py: the study's one config, and the ranges the study and its checks
share."""

from __future__ import annotations

import dataclasses

import pytest

from research import dirl_sim, takeover_check
from research.study_config import StudyConfig, range_problems


def test_the_defaults_are_in_range():
    assert range_problems(StudyConfig()) == []


@pytest.mark.parametrize(
    "change, says",
    [({"parallel": 0}, "parallel: 0 (1 or more)"),
     ({"threads": -1}, "threads -1, jobs 0: 0 (every core) or more"),
     ({"demo_noise": ()}, "demo_noise: () (one or more σ in [0, 10))"),
     ({"demo_noise": (0.0, 10.0)}, "demo_noise: (0.0, 10.0)"),
     ({"demo_noise_tau": -0.5}, "demo_noise_tau: -0.5 (seconds, 0 or more)"),
     ({"demo_noise_tau": float("inf")}, "demo_noise_tau: inf")],
)  # fmt: skip
def test_each_value_out_of_range_is_one_line_naming_it(change, says):
    problems = range_problems(dataclasses.replace(StudyConfig(), **change))
    assert len(problems) == 1 and problems[0].startswith(says), problems


def test_the_name_spells_each_field_as_the_user_set_it():
    bad = dataclasses.replace(StudyConfig(), demo_noise_tau=-1.0, parallel=0)
    problems = range_problems(bad, lambda f: f"study.{f}")
    assert [p.split(":")[0] for p in problems] == ["study.parallel", "study.demo_noise_tau"]


@pytest.mark.parametrize(
    "study_setting, check_setting, says",
    [("demo_noise=-1", "demo_noise=-1", "demo_noise: (-1.0,) (one or more σ in [0, 10))"),
     ("demo_noise_tau=-0.5", "study.demo_noise_tau=-0.5",
      "demo_noise_tau: -0.5 (seconds, 0 or more)"),
     ("parallel=0", "parallel=0", "parallel: 0 (1 or more)")],
)  # fmt: skip
def test_the_study_and_the_check_refuse_the_same_value_in_the_same_words(
    capsys, study_setting, check_setting, says
):
    """The study's parser used to accept demo_noise=-1 (only the checks refused it) and each
    spelled demo_noise_tau's range on its own; both now read range_problems."""
    lines = []
    for parse, setting in ((dirl_sim.parse, study_setting), (takeover_check.parse, check_setting)):
        with pytest.raises(SystemExit) as stop:
            parse(["--set", setting])
        assert stop.value.code == 2
        lines.append(capsys.readouterr().err.strip().splitlines()[-1])
    assert all(says in line for line in lines), lines
    assert lines[1].endswith(("study." if "study." in check_setting else "") + says)
