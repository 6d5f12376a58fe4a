"""`prism.simulate` and `prism.build_dictionary` against the `prism`
command: the same events, the same PSFs, the same refusals."""
import numpy as np
import pytest

import prism
from conftest import run_prism


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
