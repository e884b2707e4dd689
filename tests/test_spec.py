"""Campaign specs: the shipped specs parse, unknown names are errors listing the valid ones, overrides apply."""

import pytest

from harness import spec as specmod


def test_lab_spec_reproduces_the_first_lab():
    s = specmod.load("lab")
    assert s.sample_rate == 50.0 and s.Ts == pytest.approx(0.02)
    ident = [e for e in s.experiments if e.role == "identification"]
    assert [e.params.get("B") for e in ident[:4]] == [0.05, 0.10, 0.15, 0.20]
    assert [e.params.get("f") for e in ident[4:]] == [0.30, 0.35, 0.40, 0.45, 0.50]
    assert {e.duration for e in ident} == {60.0}
    assert s.plant["coulomb_torque"] == 0.044 and s.plant["n_modes"] == 2
    assert s.daq["adc_bits"] == 12 and s.daq["delay_samples"] == 1
    assert {e.signal for e in s.calibration} == {"constant", "comb", "ramp"}
    assert s.identify["fit_threshold"] == 89.0


def test_nominal_spec_is_the_textbook_rig_with_the_same_experiments():
    lab, nom = specmod.load("lab"), specmod.load("nominal")
    assert nom.plant == {"n_modes": 1} and nom.daq == {}
    assert [e.name for e in nom.all_experiments()] == [e.name for e in lab.all_experiments()]


def test_unknown_parameter_lists_valid_names():
    with pytest.raises(specmod.SpecError, match=r"unknown key\(s\) backlsh in \[plant\]; valid: .*backlash"):
        specmod.load("lab", ["plant.backlsh=0.004"])


def test_override_sets_one_parameter_and_changes_the_hash():
    base = specmod.load("lab")
    s = specmod.load("lab", ["plant.backlash=0.004", "daq.delay_samples=2"])
    assert s.plant["backlash"] == 0.004 and s.daq["delay_samples"] == 2
    assert s.sha256() != base.sha256()
    assert specmod.load("lab").sha256() == base.sha256()


@pytest.mark.parametrize(
    "override, message",
    [
        ("plant.n_modes=1.5", "must be an integer"),
        ("plant.Beq=nan", "finite number"),
        ("plant.Beq=true", "finite number"),
        ("campaign.sample_rate=-1", "sample_rate"),
        ("backlash=1", "table.name=value"),
        ("rig.backlash=1", "table must be one of"),
        ("identify.order=3", "unknown key"),
    ],
)
def test_bad_values_are_one_line_errors(override, message):
    with pytest.raises(specmod.SpecError, match=message) as exc:
        specmod.load("lab", [override])
    assert "\n" not in str(exc.value)


def test_bad_signal_and_malformed_toml(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[[experiment]]\nname = "x"\nsignal = "prbs"\nduration = 1.0\nB = 0.1\nampl = 1\n')
    with pytest.raises(specmod.SpecError, match="ampl"):
        specmod.load(p)
    p.write_text("[campaign\n")
    with pytest.raises(specmod.SpecError, match="malformed TOML"):
        specmod.load(p)
    p.write_text('[[experiment]]\nname = "x"\nsignal = "sawtooth"\nduration = 1.0\n')
    with pytest.raises(specmod.SpecError, match="sawtooth.*valid: .*prbs"):
        specmod.load(p)


def test_parse_value_reads_toml_literals():
    assert specmod.parse_value("0.004") == 0.004
    assert specmod.parse_value("2") == 2
    assert specmod.parse_value("true") is True
    assert specmod.parse_value("[1, 8]") == [1, 8]
    assert specmod.parse_value("zoh") == "zoh"
