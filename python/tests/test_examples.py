"""The scripts in examples/ run on the module and draw their figures."""
import pathlib
import subprocess
import sys

EXAMPLES = pathlib.Path(__file__).resolve().parents[2] / "examples"


def test_the_fig3_example_draws_its_figure(tmp_path):
    script = EXAMPLES / "fig3_crlb.py"
    out = tmp_path / "fig3.png"
    r = subprocess.run([sys.executable, str(script), "--quick", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.exists() and out.stat().st_size > 20000, "the figure is missing or empty"
    # One line per design, the prototype's CRLB rising with depth.
    lines = dict(line.split(":", 1) for line in r.stdout.splitlines() if ":" in line and not line.startswith("wrote"))
    proto = [float(v) for v in lines["     prototype"].split()]
    assert len(lines) == 7 and proto[-1] > proto[1]


def test_the_reconstruction_example_plots_errors_against_the_crlb(tmp_path):
    script = EXAMPLES / "reconstruct_vs_crlb.py"
    out = tmp_path / "errors.png"
    r = subprocess.run([sys.executable, str(script), "--quick", "--work", str(tmp_path / "work"), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.exists() and out.stat().st_size > 20000, "the figure is missing or empty"
    line = next(l for l in r.stdout.splitlines() if l.startswith("median 3D error"))
    # Thin lenses, 100 photons, inside the dictionary's grid: well under 1 mm.
    assert float(line.split()[3]) < 1.0, r.stdout
