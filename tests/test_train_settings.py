"""Training settings as data (issue 69, item 3): each setting's doc and allowed values beside its
default (training/setting.py), the checks, `carrt-train --settings` and docs/training.md's
tables all read from them; the research variants' settings only in research/variants/."""

from __future__ import annotations

import dataclasses
import json

import pytest

pytest.importorskip("torch")

from research.variants.config import ResearchConfig
from training import settings_doc
from training.config import (
    FROZEN,
    RESEARCH_SETTINGS,
    TrainingConfig,
    UsageError,
    apply_set,
)
from training.iterate import main, parse
from training.loop_config import FILE, TrainingLoopConfig
from training.setting import problems


def test_the_docs_tables_are_what_the_declarations_make():
    """docs/training.md's section between the markers is `python -m training.settings_doc`'s."""
    page = settings_doc.DOC.read_text()
    assert settings_doc.BEGIN in page and settings_doc.END in page
    assert settings_doc.with_section(page) == page, "run: python -m training.settings_doc"
    for spec in dataclasses.fields(TrainingConfig):
        assert f"| `{spec.name}` |" in page
    for name in RESEARCH_SETTINGS:
        assert f"`{name}`" not in settings_doc.generated()  # not carrt-train's


def test_every_setting_is_declared_with_a_doc():
    for cls in (TrainingConfig, ResearchConfig, TrainingLoopConfig):
        for spec in dataclasses.fields(cls):
            assert spec.metadata.get("doc"), f"{cls.__name__}.{spec.name} has no doc"
        assert not problems(cls()), cls  # every default is allowed


def test_settings_lists_every_setting_with_its_doc_and_default(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--settings"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    for spec in dataclasses.fields(TrainingConfig):
        default = settings_doc.value_text(spec.default)
        assert f"  {spec.name} (" in out and f") = {default}" in out, spec.name
        assert spec.metadata["doc"].split()[0] in out
    assert "imitation_steps (int) = 20000; presets: tiny 30, cpu 2000; allowed: ≥ 0" in out
    assert not any(f"  {name} (" in out for name in RESEARCH_SETTINGS)
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "--settings" in capsys.readouterr().out


def test_the_research_settings_live_in_research():
    """The ten research-only settings are ResearchConfig's, not TrainingConfig's; the product's
    list of their names (for its refusal) is exactly them."""
    product = {f.name for f in dataclasses.fields(TrainingConfig)}
    research = [f.name for f in dataclasses.fields(ResearchConfig) if f.name not in product]
    assert research == list(RESEARCH_SETTINGS) and len(research) == 10
    assert not product & set(RESEARCH_SETTINGS)


def test_research_train_lists_and_takes_its_settings(capsys):
    from research.variants.train import research_config

    cfg = research_config(["--episodes", "e", "--out", "o", "--set", "refine_search=true"])
    assert isinstance(cfg, ResearchConfig) and cfg.refine_search and cfg.dirl
    with pytest.raises(UsageError, match=None) as info:
        research_config(["--episodes", "e", "--out", "o", "--set", "outcome_temperature=0"])
    assert str(info.value) == "outcome_temperature must be > 0, got 0.0"
    with pytest.raises(SystemExit):
        research_config(["--settings"])
    assert "  counterfactual_starts (int) = 0; allowed: ≥ 0" in capsys.readouterr().out


@pytest.mark.parametrize(
    "item, message",
    [
        ("refine_lr=0", "refine_lr must be > 0, got 0.0"),  # out of range
        ("imitation_steps=-1", "imitation_steps must be >= 0, got -1"),
        ("val_fraction=1", "val_fraction must be in [0, 1), got 1.0"),
        ("world_action_inputs=every", "world_action_inputs must be one of first, all"),
        ("imitation_steps=2.5", "--set imitation_steps=2.5: not a valid int"),  # wrong type
        ("augment=maybe", "--set augment=maybe: not a valid bool"),
        ("refine_lr=nan", "--set refine_lr=nan: not a valid float"),
        ("refine_lr=inf", "--set refine_lr=inf: not a valid float"),
        ("grad_clip=-inf", "--set grad_clip=-inf: not a valid float"),
        ("refine_lrr=1", "unknown field (did you mean refine_lr?) (see carrt-train --settings)"),
        ("refine_search=true", "refine_search is a research variant: run it with research/"),
        ("counterfactual_starts=0", "counterfactual_starts is a research variant"),
        ("episodes=x", "--set episodes: unknown field"),  # a flag's, not --set's
    ],
)
def test_bad_settings_are_refused_in_one_line_naming_the_field(tmp_path, capsys, item, message):
    argv = ["--episodes", str(tmp_path), "--out", str(tmp_path / "o"), "--set", item]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert item.partition("=")[0] in err


def test_a_config_built_in_code_is_checked_the_same_way():
    """NaN passes every comparison: the declarations refuse it wherever a float is set."""
    for bad, message in [
        (dict(refine_lr=float("nan")), "refine_lr must be a finite number, got nan"),
        (dict(grad_clip=float("inf")), "grad_clip must be a finite number, got inf"),
        (dict(imitation_steps=1.5), "imitation_steps must be of type int, got 1.5"),
        (dict(augment="yes"), "augment must be of type bool, got 'yes'"),
        (dict(profile="huge"), "unknown profile 'huge'"),
    ]:
        with pytest.raises(UsageError, match=None) as info:
            dataclasses.replace(TrainingConfig(), **bad).validate()
        assert message in str(info.value), info.value
    assert apply_set(TrainingConfig(), ["refine_lr=2e-5"]).refine_lr == 2e-5
    assert set(FROZEN) <= {f.name for f in dataclasses.fields(TrainingConfig)}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--drive-seconds", "nan"], "--drive-seconds must be a finite number, got nan"),
        (["--compare-seconds", "inf"], "--compare-seconds must be a finite number, got inf"),
        (["--jobs", "0"], "--jobs must be >= 1, got 0"),
    ],
)
def test_bad_loop_flags_are_refused_by_their_declaration(tmp_path, extra, message):
    with pytest.raises(UsageError, match=None) as info:
        parse(["--episodes", str(tmp_path), "--out", str(tmp_path / "o"), "--iterations", "1",
               *extra])  # fmt: skip
    assert str(info.value) == message


def test_a_loop_saves_its_flags_beside_its_iterations(tmp_path):
    """OUT/training_loop.json holds the loop's flags; running again (resuming) rewrites it with
    the flags given, and one iteration (no --iterations) writes none."""
    out = tmp_path / "loop"
    base = ["--episodes", str(tmp_path), "--out", str(out)]
    parse([*base, "--iterations", "2", "--drive", "sim", "--drive-seconds", "5"])
    saved = json.loads((out / FILE).read_text())
    assert saved == dataclasses.asdict(
        TrainingLoopConfig(iterations=2, drive="sim", drive_seconds=5.0)
    )
    parse([*base, "--iterations", "3", "--drive", "sim", "--drive-seconds", "5"])
    assert json.loads((out / FILE).read_text())["iterations"] == 3
    parse(["--episodes", str(tmp_path), "--out", str(tmp_path / "one")])
    assert not (tmp_path / "one" / FILE).exists()
