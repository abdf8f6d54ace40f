"""The ablation of the paper's method: its variants are valid worlds, and a run that stopped
goes on from the variants it already measured."""

from __future__ import annotations

import json

import pytest

from cloud_service import ablation
from shared.paper import TABLE_I_JAMMERS
from shared.scenario import ScenarioError


def sections(scenario) -> dict:
    """The scenario's values by section, its one jammer as the section ``jammer`` (the name
    a change gives it)."""
    values = scenario.model_dump()
    (values["jammer"],) = values.pop("jammers")
    return values


def test_every_variant_changes_exactly_what_it_names(scenario):
    for variant in ablation.VARIANTS:
        world = scenario.changed(variant.scenario, variant.name)
        before, after = sections(scenario), sections(world)
        differing = {f"{section}.{key}" for section, values in after.items()
                     if isinstance(values, dict)
                     for key, value in values.items() if before[section][key] != value}
        assert differing == set(variant.scenario), variant.name
        assert world.name == variant.name


def test_a_misspelt_or_invalid_change_is_refused(scenario):
    with pytest.raises(ScenarioError, match="uav.turn_rate: no such scenario value"):
        scenario.changed({"uav.turn_rate": 90.0}, "x")
    with pytest.raises(ValueError):
        scenario.changed({"timing.step_s": -1.0}, "x")


def fake_result(name: str, success: float) -> dict:
    rates = {"success_rate": success, "disconnection_rate": 1 - success,
             "collision_rate": 0.0, "timeout_rate": 0.0}
    return {"variant": name, "change": f"change of {name}", "scenario_changes": {},
            "training_episodes": 10, "training_validation_success": success,
            "selected_episode": 10, "eval_episodes_per_setting": 2,
            "perfect_map": {**{s.label: rates for s in TABLE_I_JAMMERS}, "none": rates},
            "table_i_mean": rates, "wall_seconds": 1.0}


def test_measured_variants_are_tabulated_without_training_again(tmp_path, capsys):
    for name, success in (("shipped", 0.55), ("free-turns", 0.875)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "result.json").write_text(json.dumps(fake_result(name, success)))
    assert ablation.main(["--out", str(tmp_path), "--only", "shipped", "free-turns"]) == 0
    assert "2 variant(s) already measured, 0 to train" in capsys.readouterr().out
    table = (tmp_path / "ablation.md").read_text()
    assert "| shipped | change of shipped | 55.0 / 45.0 / 0.0 / 0.0 | 55.0 | 55.0 | 55.0 |" in table
    assert "| free-turns |" in table and "python -m cloud_service.ablation --out" in table
    assert "| the paper (Table I) | 94.6 / 3.2 / 1.9 | 94.5 / 3.3 / 2.2 |" in table
    assert "| free-turns | 87.5 / 12.5 / 0.0 | 87.5 / 12.5 / 0.0 |" in table
    assert [r["variant"] for r in json.loads((tmp_path / "ablation.json").read_text())] == [
        "shipped", "free-turns"]


def test_an_unknown_variant_is_a_one_line_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        ablation.main(["--out", str(tmp_path), "--only", "no-such"])
    assert exit_info.value.code == 2
    assert "unknown variant(s) no-such" in capsys.readouterr().err


def test_an_unknown_scenario_is_a_one_line_error(tmp_path, capsys):
    assert ablation.main(["--scenario", "no-such-world", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ablation: scenario no-such-world: no such file") and err.count("\n") == 1
