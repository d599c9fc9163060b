"""Library thread counts: set once per process, without importing torch where it is not loaded yet."""

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
