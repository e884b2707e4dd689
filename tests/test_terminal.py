"""What the command line prints fits the terminal: an 80-column terminal and a pipe (no forced 140 columns), tables
and help wrapped, never a number or an example cut with "…"; and flexjoint info's parameter list."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys


def flexjoint(*args: object, columns: int = 80, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """The command with stdout piped, as ``| less`` or a CI log sees it, in a terminal ``columns`` wide."""
    return subprocess.run(
        [sys.executable, "-m", "harness", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "COLUMNS": str(columns), **(env or {})},
    )


def _fits(text: str, columns: int = 80) -> None:
    too_wide = [x for x in text.splitlines() if len(x.rstrip()) > columns]
    assert not too_wide, too_wide
    assert "…" not in text


def _row(text: str, key: str) -> list[str]:
    line = next(x for x in text.splitlines() if x.split() and x.split()[0] == key)
    return line.split()


def test_info_lists_every_parameter_with_unit_value_default_and_range():
    r = flexjoint("info", "lab")
    assert r.returncode == 0, r.stderr
    _fits(r.stdout)
    assert _row(r.stdout, "plant.Ks") == ["plant.Ks", "N", "m/rad", "1.3", "1.3", "0..1000"]
    assert _row(r.stdout, "plant.coulomb_torque") == ["plant.coulomb_torque", "N", "m", "0.044", "0", "0..5"]
    assert _row(r.stdout, "plant.n_modes") == ["plant.n_modes", "2", "1", "1..3"]
    assert _row(r.stdout, "daq.sample_rate")[:4] == ["daq.sample_rate", "Hz", "50", "50"]
    assert "armature resistance" in r.stdout  # the description, under the name at 80 columns
    closed = flexjoint("info", "closed_loop", "--set", "plant.Ks=1.5")
    assert _row(closed.stdout, "controller.k_theta")[:4] == ["controller.k_theta", "V/rad", "9.231", "0"]
    assert _row(closed.stdout, "plant.Ks")[3:5] == ["1.5", "1.3"]
    wide = flexjoint("info", columns=160)
    assert _row(wide.stdout, "plant.Ks")[:5] == ["plant.Ks", "N", "m/rad", "1.3", "0..1000"]  # no SPEC: no value
    rows = {p["key"]: p for p in json.loads(flexjoint("info", "lab", "--json").stdout)}
    ks = rows["plant.Ks"]
    assert (ks["unit"], ks["default"], ks["min"], ks["max"], ks["spec"]) == ("N m/rad", 1.3, 0.0, 1000.0, None)
    assert rows["plant.coulomb_torque"]["spec"] == 0.044 and rows["plant.eta_g"]["range"] == "0..1"
    # the spec's uncertainty on a sheet value (the diagnosis's prior): the lab spec is a datasheet, the CU arm a lab's
    assert rows["plant.Ks"]["uncertainty"] == 1.2 and rows["plant.Beq"]["uncertainty"] == 3.0
    assert rows["plant.coulomb_torque"]["uncertainty"] is None and rows["controller.k_theta"]["uncertainty"] is None
    assert "armature resistance (10 %)" in " ".join(r.stdout.split())
    cu = flexjoint("info", "cu_flexible_arm", columns=160)
    assert _row(cu.stdout, "plant.Ks")[3:7] == ["2.2448", "1.3", "0..1000", "x2"]
    assert {k.split(".")[0] for k in rows} == {"plant", "daq", "controller"} and len(rows) > 55


def test_help_wraps_its_examples_instead_of_cutting_them():
    r = flexjoint("import", "--help")
    assert r.returncode == 0, r.stderr
    _fits(r.stdout)
    assert "time=t,Vm=u,hub=theta,tip=alpha" in r.stdout and "theta=deg,alpha=rad,u=V,t=s" in r.stdout


def test_identify_table_fits_80_columns_and_keeps_every_number(tmp_path, lab_campaign):
    """The lab's 9 datasets (a copy of the session's campaign) on a small corner of its grid: the table's shape is
    the whole grid's (test_acceptance identifies that)."""
    shutil.copytree(lab_campaign, tmp_path / "r")
    grid = ["identify.na=[3, 5]", "identify.nb=[1, 2]", "identify.nc=[1, 2]"]
    r = flexjoint("identify", tmp_path / "r", *(x for g in grid for x in ("--set", g)), env={"FLEXJOINT_WORKERS": "1"})
    assert r.returncode == 0, r.stderr
    _fits(r.stdout)
    sel = [x.split() for x in r.stdout.splitlines() if x.strip().startswith("sel (")]
    cells = [c for row in sel for c in row[2:]]
    assert len(cells) == 10 and all(len(c.split(".")[1]) == 2 for c in cells), sel  # 9 datasets + average, whole
    assert "9 square_050" in r.stdout  # the caption, not cut


def test_an_interval_has_the_digits_to_tell_its_ends_apart():
    from harness.cli import interval_text

    assert interval_text(0.49988, 0.49992) == "0.49988..0.49992"  # was 0.4999..0.4999 for a fitted 0.5
    assert interval_text(1.2345678, 1.2345679) == "1.2345678..1.2345679"
    assert interval_text(0.0041, 0.0052) == "0.0041..0.0052"


def test_the_progress_names_each_command_once(tmp_path):
    """'diagnose diagnosis screen ...' and 'case case 0' said the command twice; each line now names it once."""
    tiny = tmp_path / "tiny.toml"
    from test_executor import TINY_SPEC

    tiny.write_text(TINY_SPEC)
    one = {"FLEXJOINT_WORKERS": "1"}
    assert flexjoint("campaign", tiny, "--out", tmp_path / "r", env=one).returncode == 0
    r = flexjoint("diagnose", "--real", tmp_path / "r", "--sim", tiny, env=one)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert any(x.startswith("diagnose recalibrate ") for x in lines), r.stderr
    assert not any(x.startswith("diagnose diagnosis") for x in lines), r.stderr


def test_a_share_of_the_gap_reads_as_a_share():
    """A diagnosis round printed 'delay -40951.1 %' (a tiny excess left above the noise floor makes any misfit a huge
    negative share) and 'closed 100.5 %' (a gap below the floor): each is said in words now."""
    from harness.diagnosis.search import share_text

    assert share_text(-40951.1) == "widens it 411x"
    assert share_text(100.5) == "100 %, below the noise floor"
    assert share_text(56.34) == "56.3 %" and share_text(-22.8) == "-22.8 %" and share_text(100.0) == "100.0 %"


def test_run_says_which_stage_runs_before_it_ends(tmp_path, monkeypatch):
    """The live status line of `flexjoint run` showed the previous stage's message ("calibration: Kp ...") for the
    30 s of identification: the pipeline now says each stage as it starts (status), then its result (progress)."""
    from test_executor import TINY_SPEC

    from harness.pipeline import run_pipeline

    monkeypatch.setenv("FLEXJOINT_WORKERS", "1")
    tiny = tmp_path / "tiny.toml"
    tiny.write_text(TINY_SPEC)
    said: list[tuple[str, str]] = []
    run_pipeline(tiny, tmp_path / "r", sim=tiny, progress=lambda m: said.append(("done", m)),
                 status=lambda m: said.append(("now", m)))  # fmt: skip
    kinds = [k for k, _ in said]
    assert kinds == ["now", "done"] * (len(said) // 2), said  # every stage announced, then its result
    now = dict(zip([m for k, m in said if k == "done"], [m for k, m in said if k == "now"], strict=True))
    ident = next(m for m in now if m.startswith("identified"))
    assert now[ident].startswith("identification: ARMAX grid"), said
