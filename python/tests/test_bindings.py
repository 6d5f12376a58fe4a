"""The Python module against the `prism` command on the same inputs: the
same numbers (as the CSV writes them, 6 significant digits), the same
images, the same error messages."""
import csv
import io

import numpy as np
import pytest

import prism
from conftest import run_prism


def same_as_csv(value, field, column):
    """Whether a value equals what `prism` wrote to a CSV field (format_number:
    6 significant digits, inf, nan; empty where nothing was measured). The
    device sums in no fixed order, so two runs agree to float rounding, not
    bit for bit: numbers to 2e-5 relative (the CSV's rounding and the sums'),
    and the change against a quarter of the rays, a difference of two
    CRLBs, to 1e-6 absolute."""
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


def test_crlb_equals_the_commands_csv(tmp_path):
    out = tmp_path / "crlb.csv"
    run_prism("crlb", "--scene", "prototype", "--scene", "unifocal-f9", "--depth-mm", "5,25,45", "--x-mm", "1",
              "--y-mm", "-2", "--rays", "1024", "--binning", "16", "--csv", out)
    table = prism.crlb(["prototype", "unifocal-f9"], depth_mm=[5, 25, 45], x_mm=1, y_mm=-2, rays=1024, binning=16)
    check_rows_equal(read_csv(out), table, CRLB_COLUMNS)
    assert table["crlb_3d_mm"].dtype == np.float64 and table["flag"].dtype.kind == "U"


def test_crlb_binary_sensor_and_converge_equal_the_command(tmp_path):
    out = tmp_path / "crlb.csv"
    run_prism("crlb", "--scene", "unifocal-f15", "--depth-mm", "10", "--sensor", "binary", "--converge", "0.05",
              "--rays", "256", "--max-rays", "4096", "--binning", "32", "--csv", out)
    table = prism.crlb("unifocal-f15", depth_mm=10, sensor="binary", converge=0.05, rays=256, max_rays=4096,
                       binning=32)
    check_rows_equal(read_csv(out), table, CRLB_COLUMNS)


def test_crlb_ambiguity_equals_the_command(tmp_path):
    out = tmp_path / "crlb.csv"
    run_prism("crlb", "--scene", "prototype", "--lens-model", "thin", "--depth-mm", "30", "--rays", "1024",
              "--binning", "16", "--ambiguity", "--csv", out)
    table = prism.crlb("prototype", depth_mm=30, lens_model="thin", rays=1024, binning=16, ambiguity=True)
    check_rows_equal(read_csv(out), table,
                     CRLB_COLUMNS + ["alias_kl", "alias_x_mm", "alias_y_mm", "alias_depth_mm", "p_confusion"])
    assert np.isfinite(table["alias_kl"][0]) and table["alias_kl"][0] > 0


def test_positions_broadcast_as_numpy_does():
    table = prism.crlb("unifocal-f9", depth_mm=np.array([[10.0], [20.0]]), x_mm=[0.0, 3.0], rays=256, binning=32)
    assert list(table["depth_mm"]) == [10, 10, 20, 20]
    assert list(table["x_mm"]) == [0, 3, 0, 3]
    assert list(table["y_mm"]) == [0, 0, 0, 0]


@pytest.mark.parametrize("backend", ["vulkan", "cpu"])
def test_psf_and_its_derivatives_equal_the_commands_exr(tmp_path, backend):
    out = tmp_path / "psf.exr"
    run_prism("psf", "--scene", "prototype", "--source-mm", "1,-2,20", "--rays", "1024", "--binning", "16",
              "--derivatives", "--backend", backend, "--out", out)
    image = prism.psf("prototype", (1, -2, 20), derivatives=True, rays=1024, binning=16, backend=backend)
    for channel, key in [("Y", "b"), ("db_dx", "db_dx"), ("db_dy", "db_dy"), ("db_ddepth", "db_ddepth")]:
        expected = prism.read_exr(out, channel)
        got = image[key]
        assert got.shape == expected.shape, f"{key}: shape {got.shape} against the command's {expected.shape}"
        scale = float(np.max(np.abs(expected)))
        assert scale > 0, f"{key}: the command's image is empty"
        # The same kernel on the same inputs; the footprint's sums may come in
        # another order, so equal to float rounding of the largest value.
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * scale, err_msg=key)
    assert image["pixel_mm"] == pytest.approx(0.0069 * 16)
    values = prism.psf("prototype", (1, -2, 20), rays=1024, binning=16, backend=backend)
    np.testing.assert_allclose(values, image["b"], rtol=0, atol=1e-5 * float(values.max()))
    # The large image is NumPy's view of the engine's buffer, not a copy.
    assert image["b"].base is not None and image["db_dx"].base is image["b"].base


def test_scenes_from_names_dicts_and_files(tmp_path):
    proto = prism.scene("prototype")
    assert proto.name == "prototype" and proto.lenslet_count == 42 and proto.lens_model == "real"
    again = prism.scene(proto.to_dict())
    assert again.to_dict() == proto.to_dict()
    path = tmp_path / "mine.json"
    path.write_text('{"base": "unifocal-f9", "lens_model": "thin"}')
    assert prism.scene(str(path)).lens_model == "thin"
    table = prism.crlb(str(path), depth_mm=20, rays=256, binning=32)
    assert table["lens_model"][0] == "thin"
    assert "prototype" in prism.builtin_scenes()


def command_error(*args):
    """The message `prism` prints for a refused command, without its prefix."""
    import subprocess
    from conftest import prism_binary
    r = subprocess.run([prism_binary(), *map(str, args)], capture_output=True, text=True)
    assert r.returncode != 0, f"prism {' '.join(map(str, args))} should have failed"
    return r.stderr


def test_errors_carry_the_commands_messages(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"base": "prototype",\n "lens_model": "fresnel"}')
    with pytest.raises(prism.SceneError) as e:
        prism.scene(str(bad))
    assert str(e.value) in command_error("crlb", "--scene", bad, "--depth-mm", "10")
    with pytest.raises(ValueError):  # SceneError is a ValueError
        prism.scene({"base": "prototype", "sensor": {"pixel_um": -1}})
    with pytest.raises(prism.SceneError, match="nosuch"):
        prism.scene("nosuch")
    with pytest.raises(RuntimeError, match="depth_mm: depth -30 mm is not in front of prototype's lenses"):
        prism.crlb("prototype", depth_mm=-30)
    with pytest.raises(ValueError, match="sensor 'ideal'"):
        prism.crlb("prototype", depth_mm=10, sensor="ideal")
    with pytest.raises(TypeError):
        prism.scene(42)


def test_work_beyond_the_memory_limit_is_refused_before_it_starts():
    limit = prism.max_memory_bytes()
    try:
        prism.set_max_memory("100M")
        # A full-resolution PSF with derivatives needs about 1.4 GiB.
        with pytest.raises(prism.ResourceError, match=r"psf at binning 1 \(6696 x 4764 px\) needs an estimated"):
            prism.psf("prototype", (0, 0, 20), derivatives=True, binning=1)
        with pytest.raises(ValueError):
            prism.set_max_memory("lots")
    finally:
        prism.set_max_memory(str(limit))


def test_help_says_what_each_function_takes():
    for f in (prism.crlb, prism.psf, prism.scene, prism.read_exr, prism.devices, prism.set_max_memory):
        assert f.__doc__ and len(f.__doc__) > 40, f"{f.__name__} has no useful docstring"
    assert "binning: analyse on binning x binning sensor pixels" in prism.crlb.__doc__
    assert "{forward}" not in prism.psf.__doc__
    buffer = io.StringIO()
    import pydoc
    buffer.write(pydoc.render_doc(prism.crlb, renderer=pydoc.plaintext))
    assert "crlb_3d_mm" in buffer.getvalue()


def test_devices_are_listed_and_named():
    assert any("llvmpipe" in d for d in prism.devices())
    assert "llvmpipe" in prism.device_name("cpu")


def test_the_fig3_example_draws_its_figure(tmp_path):
    import pathlib
    import subprocess
    import sys
    script = pathlib.Path(__file__).resolve().parents[2] / "examples" / "fig3_crlb.py"
    out = tmp_path / "fig3.png"
    r = subprocess.run([sys.executable, str(script), "--quick", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.exists() and out.stat().st_size > 20000, "the figure is missing or empty"
    # One line per design, the prototype's CRLB rising with depth.
    lines = dict(line.split(":", 1) for line in r.stdout.splitlines() if ":" in line and not line.startswith("wrote"))
    proto = [float(v) for v in lines["     prototype"].split()]
    assert len(lines) == 7 and proto[-1] > proto[1]


def test_simulated_events_equal_the_commands_and_read_back_lazily(tmp_path):
    cli = tmp_path / "cli.events"
    run_prism("simulate", "--scene", "prototype", "--vertex", "1,1,31,100", "--vertex", "-4,2,12,60", "--events", "6",
              "--binning", "16", "--rays", "1024", "--jitter-mm", "0.5", "--seed", "3", "--out", cli)
    calls = []
    events = prism.simulate("prototype", [(1, 1, 31, 100), (-4, 2, 12, 60)], 6, binning=16, rays=1024, jitter_mm=0.5,
                            seed=3, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (6, 6) and len(calls) == 6
    written = tmp_path / "py.events"
    header = prism.simulate("prototype", [(1, 1, 31, 100), (-4, 2, 12, 60)], 6, binning=16, rays=1024, jitter_mm=0.5,
                            seed=3, out=written)
    assert header["event_count"] == 6 and header["binning"] == 16 and header["bytes"] == written.stat().st_size
    f = prism.EventFile(cli)
    assert len(f) == 6 and f.header["scene"] == "prototype" and f.header["grid_width"] == 419
    for a, b, c in zip(f, events, prism.EventFile(written)):
        assert a.id == b.id == c.id
        # Positions and alpha exactly; the sensor fraction, a float sum on
        # the device in no fixed order, to its rounding.
        np.testing.assert_array_equal(a.vertices[:, :4], b.vertices[:, :4])
        np.testing.assert_array_equal(a.vertices[:, :4], c.vertices[:, :4])
        np.testing.assert_allclose(a.vertices[:, 4], b.vertices[:, 4], rtol=1e-6, atol=0)
        assert a.vertices.shape == (2, 5) and a.clicks.dtype == np.uint32
        # The same PSFs and random streams: the same clicks, but for the
        # device's float sums, which come in no fixed order: a rounding can
        # flip how a Walker alias table pairs its entries and send a few
        # draws to other pixels (two runs of the command differ the same
        # way, in about one event of ten). Independent events of this
        # source share far fewer of their clicks.
        for x, y in ((a, b), (b, c)):
            same = len(np.intersect1d(x.clicks, y.clicks))
            assert same >= 0.9 * len(x.clicks) and abs(len(x.clicks) - len(y.clicks)) <= 8, f"event {x.id}"
    independent = prism.simulate("prototype", [(1, 1, 31, 100), (-4, 2, 12, 60)], 1, binning=16, rays=1024, seed=4)
    shared = len(np.intersect1d(independent[0].clicks, events[0].clicks))
    assert shared < 0.5 * len(events[0].clicks), f"another seed's event shares {shared} clicks: the check above is weak"
    assert sum(1 for _ in f) == 6, "a second iteration starts again from the first event"


def test_simulate_refuses_what_the_command_refuses(tmp_path):
    with pytest.raises(RuntimeError, match="vertices: x 40 mm lies outside prototype's volume"):
        prism.simulate("prototype", [(40, 0, 20, 100)], 1)
    with pytest.raises(RuntimeError, match="vertices less jitter_mm"):
        prism.simulate("prototype", [(0, 0, 1, 100)], 1, jitter_mm=7)
    with pytest.raises(ValueError, match=r"vertices: a \(K, 4\) array"):
        prism.simulate("prototype", [(0, 0, 20)], 1)
    bad = tmp_path / "bad.events"
    bad.write_bytes(b"not an event file")
    with pytest.raises(RuntimeError, match="bad.events"):
        prism.EventFile(bad)


def test_a_dictionary_built_from_python_equals_the_commands(tmp_path):
    grid = ["--grid-x-mm", "-5,0", "--grid-y-mm", "0", "--grid-depth-mm", "20,30"]
    run_prism("dictionary", "build", "--scene", "unifocal-f9", "--out", tmp_path / "cli", *grid, "--binning", "16",
              "--rays", "256")
    calls = []
    d = prism.build_dictionary(tmp_path / "py", "unifocal-f9", grid_x_mm=[-5, 0], grid_y_mm=0, grid_depth_mm=[20, 30],
                               binning=16, rays=256, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (4, 4) and d.report["rendered"] == 4
    cli = prism.Dictionary(tmp_path / "cli")
    assert len(d) == len(cli) == 4 and d.present() == 4 and d.scene.name == "unifocal-f9"
    np.testing.assert_array_equal(d.positions, cli.positions)
    assert d.positions[d.index(0.2, 0, 29)].tolist() == [0, 0, 30]
    assert d.manifest["grid"] == cli.manifest["grid"] and d.levels == cli.levels
    for i in range(4):
        for level in (0, 2):
            a, b = d.psf(i, level), cli.psf(i, level)
            assert a.shape == d.level_shape(level) and a.dtype == np.float32
            np.testing.assert_allclose(a, b, rtol=0, atol=2e-3 * float(b.max()), err_msg=f"entry {i} level {level}")
            assert abs(float(a.sum()) - 1) < 1e-2, "each level sums to 1 over the sensor"
    full = d.psf(1, 0)
    np.testing.assert_array_equal(d.psf(1, 0, window=(100, 50, 70, 40)), full[50:90, 100:170])
    again = prism.build_dictionary(tmp_path / "py", "unifocal-f9", grid_x_mm=[-5, 0], grid_y_mm=0,
                                   grid_depth_mm=[20, 30], binning=16, rays=256)
    assert again.report["reused"] == 4 and again.report["rendered"] == 0, "a second build resumes, rendering nothing"
    with pytest.raises(IndexError):
        d.psf(4)


def test_reconstruct_equals_the_command_from_a_file_and_from_arrays(tmp_path):
    thin = tmp_path / "thin-f9.json"
    thin.write_text('{"base": "unifocal-f9", "lens_model": "thin"}')
    dictionary = tmp_path / "dict"
    run_prism("dictionary", "build", "--scene", thin, "--out", dictionary, "--grid-x-mm", "-5,0,5", "--grid-y-mm",
              "-5,0,5", "--grid-depth-mm", "20,25,30", "--binning", "16", "--rays", "256")
    events = tmp_path / "e.events"
    run_prism("simulate", "--scene", thin, "--vertex", "1,-1,24,100", "--events", "3", "--binning", "16", "--rays",
              "1024", "--stratification", "1", "--seed", "5", "--out", events)
    columns = ["event", "vertex", "x_mm", "y_mm", "depth_mm", "alpha", "nll", "clicks", "flags", "crlb_x_mm",
               "crlb_y_mm", "crlb_z_mm", "crlb_3d_mm", "fit_pvalue"]

    def check(table, csv_path, position_mm, relative):
        rows = read_csv(csv_path)
        assert len(rows) == len(table["x_mm"]) == 3
        for i, row in enumerate(rows):
            for c in columns:
                got, want = table[c][i], row[c]
                if c == "flags":
                    assert got == want, f"row {i} flags"
                elif want == "":
                    assert np.isnan(got), f"row {i} {c}: {got} where the command wrote nothing"
                elif c in ("x_mm", "y_mm", "depth_mm"):
                    assert abs(got - float(want)) <= position_mm, f"row {i} {c}: {got} against {want}"
                elif c == "fit_pvalue":
                    assert abs(got - float(want)) <= 0.05, f"row {i} {c}: {got} against {want}"
                else:
                    assert abs(got - float(want)) <= relative * max(1.0, abs(float(want))), f"row {i} {c}: {got} vs {want}"

    # The search alone: the same answers, to the CSV's 10 digits.
    run_prism("reconstruct", "--dictionary", dictionary, "--events", events, "--vertices", "1", "--model", "none",
              "--out", tmp_path / "search.csv")
    from_file = prism.reconstruct(dictionary, events, model="none")
    check(from_file, tmp_path / "search.csv", 1e-8, 1e-8)
    listed = list(prism.EventFile(events))
    from_arrays = prism.reconstruct(prism.Dictionary(dictionary), [(e.id, None, e.clicks) for e in listed],
                                    model="none", binning=16)
    for c in columns:
        np.testing.assert_array_equal(from_file[c], from_arrays[c], err_msg=c)
    # The other backends and options reach the command's code: the same rows as the command.
    for backend, extra in (("cpu", ["--threads", "2"]), ("dense", ["--level", "2", "--precision", "half"])):
        out = tmp_path / f"search-{backend}.csv"
        run_prism("reconstruct", "--dictionary", dictionary, "--events", events, "--vertices", "1", "--model", "none",
                  "--backend", backend, *extra, "--out", out)
        kwargs = dict(threads=2) if backend == "cpu" else dict(level=2, precision="half")
        check(prism.reconstruct(dictionary, events, model="none", backend=backend, **kwargs), out, 1e-8, 1e-8)
    # With the refinement (the thin-lens scene's model): the device's sums
    # may come in another order, so the same optimum to 1e-3 mm.
    run_prism("reconstruct", "--dictionary", dictionary, "--events", events, "--vertices", "1", "--out",
              tmp_path / "refined.csv")
    calls = []
    refined = prism.reconstruct(dictionary, prism.EventFile(events), progress=lambda d, t: calls.append((d, t)))
    check(refined, tmp_path / "refined.csv", 1e-3, 1e-3)
    assert calls[-1] == (3, 3)
    assert np.all(np.abs(refined["depth_mm"] - 24) < 1.0) and np.all(np.isfinite(refined["crlb_3d_mm"]))


def test_reconstruct_refuses_bad_events_with_the_commands_messages(tmp_path):
    thin = tmp_path / "thin-f9.json"
    thin.write_text('{"base": "unifocal-f9", "lens_model": "thin"}')
    dictionary = tmp_path / "dict"
    run_prism("dictionary", "build", "--scene", thin, "--out", dictionary, "--grid-x-mm", "0", "--grid-y-mm", "0",
              "--grid-depth-mm", "20", "--binning", "16", "--rays", "64")
    with pytest.raises(ValueError, match="strictly increasing"):
        prism.reconstruct(dictionary, [(0, None, [5, 3])], model="none")
    with pytest.raises(ValueError, match="lies beyond the 419 x 298 click grid of binning 16"):
        prism.reconstruct(dictionary, [(0, None, [10**6])], model="none")
    with pytest.raises(RuntimeError, match="binning"):
        prism.reconstruct(dictionary, [(0, None, [1, 2])], model="none", binning=3)
    with pytest.raises(ValueError, match="vertices: 9"):
        prism.reconstruct(dictionary, [], vertices=9)


def test_the_reconstruction_example_plots_errors_against_the_crlb(tmp_path):
    import pathlib
    import subprocess
    import sys
    script = pathlib.Path(__file__).resolve().parents[2] / "examples" / "reconstruct_vs_crlb.py"
    out = tmp_path / "errors.png"
    r = subprocess.run([sys.executable, str(script), "--quick", "--work", str(tmp_path / "work"), "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    assert out.exists() and out.stat().st_size > 20000, "the figure is missing or empty"
    line = next(l for l in r.stdout.splitlines() if l.startswith("median 3D error"))
    # Thin lenses, 100 photons, inside the dictionary's grid: well under 1 mm.
    assert float(line.split()[3]) < 1.0, r.stdout


def test_device_work_releases_the_gil():
    import threading
    done = threading.Event()
    result = {}

    def work():
        result["b"] = prism.psf("prototype", (0, 0, 20), rays=4096, binning=4)
        done.set()

    t = threading.Thread(target=work)
    t.start()
    spins = 0
    while not done.is_set():
        spins += 1  # runs only while the render has let go of the GIL
    t.join()
    assert result["b"].sum() > 0
    assert spins > 1000, f"the main thread ran {spins} loop iterations while the device worked"
