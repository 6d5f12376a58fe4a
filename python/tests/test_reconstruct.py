"""`prism.reconstruct` against `prism reconstruct`: the same rows from a file
and from arrays, the same refusals."""
import numpy as np
import pytest

import prism
from conftest import run_prism, read_csv


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
    for backend, extra in (("cpu", ["--threads", "2"]),
                           ("dense", ["--level", "2", "--precision", "half", "--dark-rate", "1e-4"])):
        out = tmp_path / f"search-{backend}.csv"
        run_prism("reconstruct", "--dictionary", dictionary, "--events", events, "--vertices", "1", "--model", "none",
                  "--backend", backend, *extra, "--out", out)
        kwargs = dict(threads=2) if backend == "cpu" else dict(level=2, precision="half", dark_rate=1e-4)
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
    with pytest.raises(ValueError, match="dark_rate: 0 must be > 0"):
        prism.reconstruct(dictionary, [], dark_rate=0)
    with pytest.raises(ValueError, match="search_dark_rate: -1 must be >= 0"):
        prism.reconstruct(dictionary, [], search_dark_rate=-1)
