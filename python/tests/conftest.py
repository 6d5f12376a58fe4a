"""The bindings' tests run as the C++ suite does: on lavapipe with the
Khronos validation layer on, unless the environment says otherwise, and fail
when the layer printed anything. Beside the fixture, the helpers every test
file shares: running `prism` and comparing its CSVs with the module's."""
import csv
import os
import shutil
import subprocess

import numpy as np
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


def command_error(*args):
    """The message `prism` prints for a refused command, without its prefix."""
    r = subprocess.run([prism_binary(), *map(str, args)], capture_output=True, text=True)
    assert r.returncode != 0, f"prism {' '.join(map(str, args))} should have failed"
    return r.stderr


def same_as_csv(value, field, column):
    """Whether a value equals what `prism` wrote to a CSV field (format_number:
    6 significant digits, inf, nan; empty where nothing was measured). The
    device sums in no fixed order, so two runs agree to float rounding, not
    bit for bit: numbers to 2e-5 relative (the CSV's rounding and the sums'),
    and the change against a quarter of the rays, a difference of two
    CRLBs, to 1e-6 absolute. The ambiguity's columns come from an iterative
    descent that such rounding can stop a step earlier or later (1e-4 of D
    between two runs): D to 1e-3 relative, the impostor's position to 0.02 mm,
    p_confusion to 5%."""
    if isinstance(value, (str, np.str_)):
        return str(value) == field
    v = float(value)
    if field == "":
        return np.isnan(v)
    expected = float(field)  # also "inf" and "nan"
    if np.isnan(expected) or np.isinf(expected):
        return np.isnan(v) if np.isnan(expected) else v == expected
    if column == "change_vs_quarter_rays":
        return abs(v - expected) <= 1e-6
    if column in ("alias_x_mm", "alias_y_mm", "alias_depth_mm"):
        return abs(v - expected) <= 0.02
    if column in ("alias_kl", "p_confusion"):
        return abs(v - expected) <= (1e-3 if column == "alias_kl" else 0.05) * abs(expected)
    return abs(v - expected) <= 2e-5 * abs(expected)


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def check_rows_equal(cli_rows, table, columns):
    assert len(cli_rows) == len(table["crlb_3d_mm"]), "row counts differ"
    for i, row in enumerate(cli_rows):
        for c in columns:
            assert same_as_csv(table[c][i], row[c], c), f"row {i} column {c}: python {table[c][i]!r}, prism {row[c]!r}"


CRLB_COLUMNS = ["scene", "x_mm", "y_mm", "depth_mm", "photons", "crlb_x_mm", "crlb_y_mm", "crlb_z_mm", "crlb_3d_mm",
                "lens_model", "rays_per_lenslet", "change_vs_quarter_rays", "flag"]


@pytest.fixture(autouse=True, scope="session")
def validation_layer_silent():
    yield
    messages = prism.validation_messages()
    assert not messages, f"the Vulkan validation layer printed {len(messages)} message(s), first: {messages[0]}"
