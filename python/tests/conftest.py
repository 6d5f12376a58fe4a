"""The bindings' tests run as the C++ suite does: on lavapipe with the
Khronos validation layer on, unless the environment says otherwise, and fail
when the layer printed anything."""
import os
import shutil
import subprocess

import pytest

os.environ.setdefault("PRISM_DEVICE", "cpu")
os.environ.setdefault("PRISM_VALIDATION", "1")

import prism  # noqa: E402  (after the environment above)


def prism_binary():
    """The `prism` command of the same build (ctest sets PRISM_BINARY)."""
    path = os.environ.get("PRISM_BINARY") or shutil.which("prism")
    if not path:
        pytest.fail("set PRISM_BINARY to the build's prism command (build/host/prism)")
    return path


def run_prism(*args):
    """Runs the prism command; its output, or a failure that shows it."""
    r = subprocess.run([prism_binary(), *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.fail(f"prism {' '.join(map(str, args))} exited {r.returncode}:\n{r.stdout}\n{r.stderr}")
    return r.stdout


@pytest.fixture(autouse=True, scope="session")
def validation_layer_silent():
    yield
    messages = prism.validation_messages()
    assert not messages, f"the Vulkan validation layer printed {len(messages)} message(s), first: {messages[0]}"
