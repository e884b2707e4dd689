"""Campaign specs: the shipped specs parse, unknown names are errors listing the valid ones, overrides apply."""

import pytest

from harness import spec as specmod
from harness.executor import Executor
from harness.machine import WORKERS_ENV, default_workers, machine_memory


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


def test_bundled_specs_have_names_and_descriptions():
    found = specmod.bundled_specs()
    assert {"lab", "nominal", "blind"} <= set(found)
    assert all(found.values()) and "first lab" in found["lab"]
    assert specmod.resolve_path("lab") == specmod.SPEC_DIR / "lab.toml"


def test_missing_spec_names_the_bundled_ones(tmp_path):
    bundled = "blind, blind_closed, closed_loop, cu_flexible_arm, lab, nominal"
    with pytest.raises(specmod.SpecError, match=rf"spec nope not found .*bundled: {bundled}"):
        specmod.load("nope")
    with pytest.raises(specmod.SpecError, match="is a directory"):
        specmod.load(tmp_path)


def test_a_bundled_name_wins_over_a_directory_of_that_name(tmp_path, monkeypatch):
    """``flexjoint bench`` run where a blind test left ./blind used to fail: "spec blind is a directory"."""
    (tmp_path / "blind").mkdir()
    monkeypatch.chdir(tmp_path)
    assert specmod.resolve_path("blind") == specmod.SPEC_DIR / "blind.toml"


def test_spec_loader_honours_flexjoint_fmu_src(tmp_path, monkeypatch):
    """The parameter names a spec may set come from the FMU source tree the build uses, $FLEXJOINT_FMU_SRC too."""
    import shutil

    from harness.fmu.sources import bundled_dir

    src = tmp_path / "fmus"
    shutil.copytree(bundled_dir("fmus"), src)
    xml = src / "flexjoint" / "modelDescription.xml"
    xml.write_text(xml.read_text().replace('name="backlash"', 'name="gear_play"'))
    monkeypatch.setenv("FLEXJOINT_FMU_SRC", str(src))
    assert specmod.load("lab", ["plant.gear_play=0.004"]).plant["gear_play"] == 0.004
    with pytest.raises(specmod.SpecError, match="unknown key.*backlash.*gear_play"):
        specmod.load("lab", ["plant.backlash=0.004"])
    monkeypatch.setenv("FLEXJOINT_FMU_SRC", str(tmp_path / "nowhere"))
    with pytest.raises(specmod.SpecError, match="nowhere/flexjoint/modelDescription.xml is missing"):
        specmod.load("lab")
    monkeypatch.delenv("FLEXJOINT_FMU_SRC")
    assert "backlash" in specmod.fmu_parameters("flexjoint")


def test_memory_estimate_counts_samples_columns_and_work():
    s = specmod.load("lab")
    est = specmod.memory_estimate(s, workers=2)
    n = [round(e.duration * s.sample_rate) for e in s.all_experiments()]
    cols = [8 if e.signal == "comb" else 6 for e in s.all_experiments()]
    assert est["samples"] == sum(n) and est["experiments"] == len(n) and est["columns"] == [6, 8]
    assert est["data"] == 8 * sum(a * b for a, b in zip(n, cols, strict=True))
    assert est["work"] == 8 * specmod.RK4_WORK_ARRAYS * sum(sorted(n)[-2:])
    assert est["bytes"] == est["data"] + est["work"] < 10 * 2**20  # the lab campaign needs a few MiB
    assert specmod.check_memory(s, workers=2, available=2**30) == est
    with pytest.raises(specmod.SpecError, match=r"needs ~[\d.]+ MiB of memory .* this machine has 1 MiB") as e:
        specmod.check_memory(s, workers=2, available=2**20)
    assert "this machine has" in str(e.value) and "\n" not in str(e.value)


def test_memory_estimate_runs_as_many_experiments_at_once_as_the_executor_starts(monkeypatch):
    """By default the estimate counts the experiments the executor runs at once: its own default worker count
    (FLEXJOINT_WORKERS when set), at most one per experiment."""
    s = specmod.load("lab")
    n = len(s.all_experiments())
    for env in (None, "3", "1"):
        if env is None:
            monkeypatch.delenv(WORKERS_ENV, raising=False)
        else:
            monkeypatch.setenv(WORKERS_ENV, env)
        with Executor(backend="processes") as ex:  # the pool's size, known before any process starts
            started = ex.n_workers
        assert started == default_workers() and (env is None or started == int(env))
        est = specmod.memory_estimate(s)
        assert est["workers"] == min(n, started) and est == specmod.memory_estimate(s, workers=started)
    monkeypatch.setenv(WORKERS_ENV, "3")
    one = specmod.from_dict({**s.raw, "experiment": s.raw["experiment"][:1], "calibration": []}, s.path)
    assert specmod.memory_estimate(one)["workers"] == 1  # simulate_spec runs a lone experiment serially


def test_a_campaign_larger_than_the_machine_is_refused_before_any_allocation():
    """sample_rate = 1e9 would need tens of TiB; refused with the estimate, before a signal is generated."""
    assert machine_memory() > 2**28
    with pytest.raises(specmod.SpecError, match=r"needs ~[\d.]+ TiB of memory .* this machine has [\d.]+ GiB"):
        specmod.load("lab", ["campaign.sample_rate=1e9"])
