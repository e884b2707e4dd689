"""numpy's and OpenBLAS's kernels pinned to x86-64 with AVX2 (harness.numerics): in a fresh process, in the suite's
own processes (the pytest plugin), in the command line's, never over a user's own choice."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from harness import numerics

needs_avx2 = pytest.mark.skipif(not numerics.pinnable(), reason="pinned only on Linux x86-64 with AVX2 and FMA")
PROBE = (  # what a process computes with: OpenBLAS's kernels, numpy's loop of exp
    "import json, threadpoolctl, numpy as np; "
    "print(json.dumps([threadpoolctl.threadpool_info()[0]['architecture'], "
    "np.lib.introspect.opt_func_info(func_name='^exp$', signature='float64')['exp']['dd']['current']]))"
)


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}


def test_numpys_names_of_its_avx512_targets_follow_its_version():
    assert numerics.avx512_features("2.4.6") == "X86_V4 AVX512_ICL AVX512_SPR"
    assert numerics.avx512_features("3.0.0rc1") == "X86_V4 AVX512_ICL AVX512_SPR"
    assert numerics.avx512_features("1.26.4").split()[:3] == ["AVX512F", "AVX512CD", "AVX512_KNL"]


def test_a_users_own_choice_is_kept_and_a_loaded_numpy_is_said():
    env = {"OPENBLAS_CORETYPE": "Zen"}
    took = numerics.pin_numerics(env)
    assert took is False  # not this process's environment (and numpy is loaded here): nothing it computes is pinned
    if numerics.pinnable():
        assert env["OPENBLAS_CORETYPE"] == "Zen"
        assert env["NPY_DISABLE_CPU_FEATURES"] == numerics.avx512_features(np.__version__)


@needs_avx2
def test_a_fresh_process_pinned_before_numpy_computes_with_avx2_kernels():
    """Pinned, a process uses OpenBLAS's Haswell kernels and numpy's X86_V3 loop of exp, whatever the CPU has beyond
    AVX2 (this one: AVX-512, where OpenBLAS may pick SkylakeX and numpy its X86_V4 loops)."""
    code = f"import harness.numerics as n; assert n.pin_numerics(); {PROBE}"
    out = subprocess.run([sys.executable, "-c", code], env=_clean_env(), capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == ["Haswell", "X86_V3"]


@needs_avx2
def test_the_suite_and_the_command_line_compute_pinned():
    """The pytest plugin pinned this process before the conftest files loaded numpy; the command line pins first
    thing (what it computed with, read as it exits), and the processes it starts inherit the variables."""
    assert os.environ["OPENBLAS_CORETYPE"] == numerics.OPENBLAS_CORE
    info = np.lib.introspect.opt_func_info(func_name="^exp$", signature="float64")
    assert info["exp"]["dd"]["current"] == "X86_V3"
    code = "\n".join(
        [
            "import atexit, sys",
            "def probe():",
            f"    {PROBE}",
            "atexit.register(probe)",  # what it computed with, read as it exits
            "sys.argv = ['flexjoint', 'specs']",
            "from harness.__main__ import main",
            "main()",
        ]
    )
    out = subprocess.run([sys.executable, "-c", code], env=_clean_env(), capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.splitlines()[-1]) == ["Haswell", "X86_V3"]
