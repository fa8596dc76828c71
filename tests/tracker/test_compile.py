"""The install-time compile step (tracker.compile): it sees whether numba's cache holds compiled kernels,
and finds every cached kernel of the packages."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numba

from tracker import compile as C

SRC = Path(C.__file__).resolve().parents[1]


def _run(code, cache_dir):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PYTHONPATH=str(SRC))
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout.strip()


def test_an_empty_cache_is_cold_and_says_so_once(tmp_path):
    """With no compiled kernel in the cache, the first call's note names the compile step; nothing was
    compiled by asking (the cache folder stays empty of tracker kernels)."""
    out = _run("""
        from tracker.compile import cold_message, is_cold
        print(is_cold()); print(cold_message())
        """, tmp_path)
    cold, message = out.splitlines()
    assert cold == "True"
    assert "tracker compile" in message and "min" in message
    assert not list(tmp_path.rglob("*fit_kernel*.nbc"))


def test_the_cache_index_sees_a_compiled_kernel(tmp_path):
    """The check reads numba's index: empty before a cached kernel's first call, one signature after."""
    mod = tmp_path / "kmod.py"
    mod.write_text("from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n")
    out = _run(f"""
        import sys; sys.path.insert(0, {str(tmp_path)!r})
        import kmod
        from tracker.compile import _cache_index
        print(len(_cache_index(kmod.twice)))
        kmod.twice(1.5)
        print(len(_cache_index(kmod.twice)))
        """, tmp_path / "cache")
    assert out.splitlines() == ["0", "1"]


def test_every_kernels_module_is_found():
    """Each stage's kernels module contributes its cached kernels to the count `tracker compile` reports."""
    found = C.kernels()
    modules = {m for m, _, _ in found}
    for name in ("tracker._fit_kernels", "tracker._correspond_kernels", "tracker._search_kernels",
                 "tracker._observe_kernels", "tracker._silhouette_kernels", "tracker._wrist_kernels",
                 "handmodel.kinematics", "handmodel._solver_kernels", "handmodel._geometry_kernels"):
        assert name in modules, name
    assert ("tracker._fit_kernels", "fit_kernel") in {(m, f) for m, f, _ in found}
    assert all(isinstance(d, numba.core.registry.CPUDispatcher) for _, _, d in found)
