"""The family of plausible plants (simulator.plant.family): every unsourced constant has
the bracket its basis allows, every shipped variant loads and stays inside the
brackets, and ``--plant-variant`` reaches the plant of ``generate`` (docs/plant.md)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from simulator.cli import main
from simulator.plant import load_constants, load_plant
from simulator.plant.constants import PlantError, sources
from simulator.plant.family import NOMINAL, VARIANTS_DIR, brackets, load_variant, variant_constants, variant_names

ROOT = Path(__file__).resolve().parents[1]
NEEDS_BRACKET = re.compile(r"\[NO SOURCE|\[unverified\]|\btuned\b")


def test_every_unsourced_unverified_or_tuned_constant_has_a_bracket_around_its_value():
    unbracketed = [name for name, e in sources().items() if NEEDS_BRACKET.search(e["source"]) and "low" not in e]
    assert unbracketed == []
    for name, (low, value, high) in brackets().items():
        assert low <= value <= high and low < high, name
        assert sources()[name].get("bracket", "").strip(), f"{name}: a bracket says why"


def test_docs_plant_shows_every_bracket():
    doc = (ROOT / "docs" / "plant.md").read_text()
    for name, (low, _, high) in brackets().items():
        row = next(line for line in doc.splitlines() if line.startswith(f"| `{name}` |"))
        assert f"{low:g} – {high:g}" in row, f"{name}: docs/plant.md shows no bracket {low:g} – {high:g}"


def test_no_constant_cites_a_note_outside_the_repository():
    text = (ROOT / "simulator" / "plant" / "constants.toml").read_text() + (ROOT / "docs" / "plant.md").read_text()
    assert "plant-physics-sources" not in text and "paper-findings" not in text


@pytest.mark.parametrize("name", [n for n in variant_names() if n != NOMINAL])
def test_every_variant_loads_changes_something_and_stays_in_its_brackets(name):
    variant = load_variant(name)
    assert variant.basis and variant.changes
    k, nominal = variant_constants(name), load_constants()
    assert k != nominal
    table = brackets()
    for field, value in variant.changes.items():
        low, _, high = table[field.replace("_", ".", 1)]
        assert low <= getattr(k, field) == value <= high


def test_nominal_is_the_constants_file():
    assert variant_names()[0] == NOMINAL
    assert variant_constants(NOMINAL) == load_constants()


def test_a_variant_outside_a_bracket_or_unknown_is_refused(tmp_path, monkeypatch):
    (tmp_path / "too-sharp.toml").write_text('basis = "x"\n[orifice.cd_turbulent]\nvalue = 0.3\n')
    monkeypatch.setattr("simulator.plant.family.VARIANTS_DIR", tmp_path)
    with pytest.raises(PlantError, match="outside its bracket"):
        load_variant("too-sharp")
    with pytest.raises(PlantError, match="unknown"):
        load_variant("no-such")


def test_generate_takes_a_plant_variant_and_refuses_it_for_the_model(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["generate", "--physics", "plant", "--plant-variant", "low-cd", "--experiments", "n",
                 "--periods", "1", "--rate", "500", "--out", str(out)]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["constants"]["orifice_cd_turbulent"] == pytest.approx(0.61)
    assert main(["generate", "--plant-variant", "low-cd", "--out", str(tmp_path / "m")]) == 2
    assert "--plant-variant: only with --physics plant" in capsys.readouterr().err
    with pytest.raises(SystemExit) as refused:
        main(["generate", "--physics", "plant", "--plant-variant", "no-such", "--out", str(tmp_path / "x")])
    assert refused.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_load_plant_applies_a_variant_beneath_a_production_unit():
    assert load_plant(variant="natural-convection-only").k.heat_forced_coefficient == 0.0
    unit = load_plant("worn-seal", 3, variant="averaged-seal").k
    assert unit.seal_breakaway_ratio == 1.0 and unit.seal_preload_force != 126.0


def test_the_variants_directory_ships_with_the_package():
    assert VARIANTS_DIR.is_dir()
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert "plant/variants/*.toml" in pyproject and "plant/constants.toml" in pyproject


def test_serve_takes_the_variant_option_and_refuses_it_for_the_model_before_any_endpoint_opens(capsys):
    assert main(["serve", "--plant-variant", "low-cd", "--modbus", "tcp://127.0.0.1:0",
                 "--daq", "socket://127.0.0.1:0"]) == 2
    assert capsys.readouterr().err.startswith("error: --plant-variant: only with --physics plant")
