"""Library thread counts: set once per process, without importing torch where it is not loaded yet."""

import os
import subprocess
import sys

SNIPPET = """
import sys
from lightstage.threads import set_library_threads
{before}
set_library_threads(1)
loaded = "torch" in sys.modules
import torch
print(loaded, torch.get_num_threads())
"""


def _run(before: str) -> str:
    code = SNIPPET.format(before=before)
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()


def test_torch_not_imported_only_for_its_threads_but_still_gets_one():
    assert _run("") == ["False", "1"]


def test_torch_already_loaded_gets_its_threads_set():
    assert _run("import torch; torch.set_num_threads(2)") == ["True", "1"]


def _spin(env_value: str | None) -> str:
    """GOMP_SPINCOUNT as a fresh process sees it after `import lightstage, torch` (`env_value`: the user's)."""
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    if env_value is not None:
        env["GOMP_SPINCOUNT"] = env_value
    code = "import os, lightstage, torch; print(os.environ.get('GOMP_SPINCOUNT'))"
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    ).stdout


def test_importing_lightstage_bounds_openmp_spin_before_torch_loads():
    """The package root shortens GNU OpenMP's spin-wait (it starves the hash grid's kernel threads otherwise),
    and a value the user set wins."""
    from lightstage.threads import OPENMP_SPIN_ENV

    assert _spin(None).strip() == OPENMP_SPIN_ENV["GOMP_SPINCOUNT"]
    assert _spin("123").strip() == "123"
