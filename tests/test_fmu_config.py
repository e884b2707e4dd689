"""Each model's config.h against its modelDescription.xml: the C side's variable table (names, value references,
types, start values) equals the XML that the Python side reads (harness.fmu.modeldesc)."""

from __future__ import annotations

import re

import pytest

from harness.fmu import modeldesc
from harness.fmu.sources import fmu_source_dir

LISTS = {"REAL_PARAMETERS": ("parameter", "Real"), "INTEGER_PARAMETERS": ("parameter", "Integer")}
LISTS |= {"INPUTS": ("input", "Real"), "OUTPUTS": ("output", "Real")}
ARRAYS = "ARRAY_PARAMETERS"  # X(name, first value reference, rows, columns): Real parameters name[i,j] or name[i]


def array_elements(entry: tuple[str, ...], defines: dict[str, int]) -> dict[str, int]:
    """{XML name: value reference} of an array parameter's elements, row-major from its first value reference."""
    name, vr0, rows, cols = entry[0], int(entry[1]), *(defines.get(x, 0) or int(x) for x in entry[2:4])
    out = {}
    for i in range(rows):
        for j in range(cols):
            idx = f"{j + 1}" if rows == 1 else f"{i + 1}" if cols == 1 else f"{i + 1},{j + 1}"
            out[f"{name}[{idx}]"] = vr0 + i * cols + j
    return out


def config_lists(text: str) -> dict[str, list[tuple[str, ...]]]:
    """{list name: [(name, value reference[, start]), ...]} of the ``#define LIST(X) X(..) X(..)`` lists."""
    out = {}
    for m in re.finditer(r"^#define\s+(\w+)\(X\)((?:.*\\\n)*.*)$", text, re.M):
        out[m.group(1)] = [tuple(a.strip() for a in e.split(",")) for e in re.findall(r"X\(([^)]*)\)", m.group(2))]
    return out


@pytest.mark.parametrize("model", ["flexjoint", "daq", "controller", "signal"])
def test_config_h_variable_lists_equal_the_xml(model):
    src = fmu_source_dir() / model
    md = modeldesc.read(src)
    text = (src / "config.h").read_text()
    lists = config_lists(text)
    arrays = lists.pop(ARRAYS, [])
    assert set(lists) == set(LISTS)
    seen = {}
    defines = {k: int(v) for k, v in re.findall(r"^#define\s+(\w+)\s+(\d+)\s*$", text, re.M)}
    for entry in arrays:
        for name, vr in array_elements(entry, defines).items():
            var = md.variables[name]
            assert (var.value_reference, var.causality, var.type, var.start) == (vr, "parameter", "Real", 0.0), name
            seen[name] = vr
    for name, (causality, kind) in LISTS.items():
        for entry in lists[name]:
            var = md.variables[entry[0]]
            assert (var.value_reference, var.causality, var.type) == (int(entry[1]), causality, kind), entry
            if causality == "parameter":
                assert float(entry[2]) == var.start, entry  # the compiled default is the XML's start value
            seen[entry[0]] = var.value_reference
    assert seen == {n: v.value_reference for n, v in md.variables.items()}  # every variable, none twice
    params = [e[0] for e in lists["REAL_PARAMETERS"] + lists["INTEGER_PARAMETERS"]]
    params += [n for e in arrays for n in array_elements(e, defines)]
    assert sorted(params, key=lambda n: md.variables[n].value_reference) == list(md.parameters())


def test_armax_value_references_equal_the_xml():
    src = fmu_source_dir() / "armax"
    cfg = (src / "config.h").read_text()
    nmax = int(re.search(r"^#define\s+NMAX\s+(\d+)", cfg, re.M).group(1))
    vrs = {k: int(v) for k, v in re.findall(r"\b(vr_\w+|VR_[ABC])\s*=\s*(\d+)", cfg)}
    want = {k.removeprefix("vr_"): v for k, v in vrs.items() if k.startswith("vr_")}
    want |= {f"a[{i}]": vrs["VR_A"] + i for i in range(1, nmax + 1)}
    want |= {f"b[{j}]": vrs["VR_B"] + j for j in range(nmax + 1)}
    want |= {f"c[{i}]": vrs["VR_C"] + i for i in range(1, nmax + 1)}
    assert {n: v.value_reference for n, v in modeldesc.read(src).variables.items()} == want


def test_a_mismatch_is_caught():
    text = "#define INPUTS(X) \\\n    X(u, 30) \\\n    X(tau_tip, 32)\n"
    assert config_lists(text) == {"INPUTS": [("u", "30"), ("tau_tip", "32")]}
    md = modeldesc.read(fmu_source_dir() / "flexjoint")
    assert md.variables["tau_tip"].value_reference != 32
