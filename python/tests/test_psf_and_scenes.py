"""PSFs, scenes, errors, help and devices: the module against the `prism`
command on the same inputs (the same images, the same error messages)."""
import io

import numpy as np
import pytest

import prism
from conftest import run_prism, command_error


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
