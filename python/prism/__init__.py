"""PRISM: plenoptic imaging of scintillation events, from Python.

The same engine as the `prism` command: the same scenes, defaults, kernels
and error messages, with NumPy arrays in and out. Every function that takes
a scene takes a built-in name ("prototype", "unifocal-f9", ...; see
builtin_scenes()), the path of a JSON scene file, a dict in the scene-file
schema (README "Scene files"), or a Scene.

Device work runs on a Vulkan device ("auto": a GPU if present, else Mesa's
lavapipe on the CPU; `device=` or $PRISM_DEVICE chooses) with the GIL
released; backend="cpu" runs the double-precision reference instead.

Units are in the names: _mm millimetres, _um micrometres; photons are
expected counts. Errors are Python exceptions carrying the command's
messages: SceneError (a ValueError) for a scene that cannot be used,
ResourceError (a MemoryError) for work beyond the memory limit
($PRISM_MAX_MEMORY), DeviceError for Vulkan, ValueError for bad arguments.
"""

import json as _json
import os as _os

import numpy as _np

from . import _core
from ._core import DeviceError, ResourceError, Scene, SceneError

__all__ = [
    "Scene", "SceneError", "ResourceError", "DeviceError", "scene", "builtin_scenes", "devices", "device_name",
    "validation_messages", "crlb", "ambiguity", "psf", "read_exr", "set_max_memory", "max_memory_bytes", "Event", "EventFile",
    "simulate", "Dictionary", "build_dictionary", "reconstruct",
]

_FORWARD_DOC = """
    rays: rays (footprint: aperture cells) per 3 mm lenslet, rounded up to an
        even square of strata; other lens sizes get the same per mm^2; 0: the
        splat's converged default (docs/model.md "Convergence").
    binning: analyse on binning x binning sensor pixels (6.9 um each).
    splat: "footprint" (each aperture cell's image gives box pixels their
        exact area) or "point" (each ray splatted bilinearly, the paper's way).
    stratification: 0 the default strata; another number another
        stratification of the same apertures.
    lens_model: None (the scene's own), "thin" or "real".
    photons_emitted: photons emitted by the source; None: the scene's (6280
        for the built-ins).
    backend: "vulkan" (kernels on the device) or "cpu" (double reference).
    device: None ($PRISM_DEVICE or auto), "auto", "gpu", "cpu", an index or
        part of a device name (see devices())."""


def _doc(f):
    f.__doc__ = f.__doc__.replace("{forward}", _FORWARD_DOC.strip("\n"))
    return f


def scene(spec):
    """A Scene from a built-in name, a JSON scene file's path, a dict in the
    scene-file schema, or a Scene (returned as it is).

    Raises SceneError naming the file (and line) or the field that is wrong,
    as the command line does.
    """
    if isinstance(spec, Scene):
        return spec
    if isinstance(spec, dict):
        try:
            text = _json.dumps(spec, allow_nan=False)
        except (TypeError, ValueError) as e:
            raise SceneError(f"scene dict: {e}") from None
        return _core.scene_from_json_text(text)
    if isinstance(spec, str):
        return _core.load_scene(spec)
    raise TypeError(f"scene: a name, a path, a dict or a Scene, not {type(spec).__name__}")


def _scene_dict(self):
    """The scene as a dict in the scene-file schema (what `prism` writes in
    a dictionary's manifest)."""
    return _json.loads(self.json_text())


Scene.to_dict = _scene_dict
Scene.__repr__ = lambda self: (f"<prism.Scene {self.name!r}: {self.lenslet_count} lenslets, "
                               f"{self.lens_model} lenses, {self.photons_emitted:g} photons emitted>")


def builtin_scenes():
    """The names of the built-in scenes (the paper's designs)."""
    return list(_core.builtin_scene_names())


def devices():
    """The Vulkan devices present, as "index: name [type]"."""
    return list(_core.list_devices())


def device_name(device=None):
    """The device a call with this `device=` runs on, described as the
    command line's "# device:" line does."""
    return _core.describe_device(device or "")


def validation_messages():
    """Messages of the Khronos validation layer so far (warnings and errors),
    from every device this process used. The layer is on when
    $PRISM_VALIDATION=1 was set before the first device call."""
    return list(_core.validation_messages())


def _forward(rays, binning, splat, stratification, lens_model, photons_emitted, backend, device, estimator):
    if photons_emitted is not None and not (_np.isfinite(photons_emitted) and photons_emitted > 0):
        raise ValueError(f"photons_emitted: {photons_emitted} must be a finite number > 0")
    if not 1 <= int(binning) <= 1024:
        raise ValueError(f"binning: {binning} is not in 1..1024")
    if not 0 <= int(rays) <= 1 << 24:
        raise ValueError(f"rays: {rays} is not in 0..{1 << 24}")
    if int(stratification) < 0:
        raise ValueError(f"stratification: {stratification} must be >= 0")
    if lens_model not in (None, "thin", "real"):
        raise ValueError(f"lens_model {lens_model!r}: use None, 'thin' or 'real'")
    return dict(rays=int(rays), binning=int(binning), splat=str(splat), stratification=int(stratification),
                lens_model=lens_model or "", photons=float(photons_emitted or 0), backend=str(backend),
                device=device or "", estimator=str(estimator))


@_doc
def crlb(scene="prototype", depth_mm=25.0, x_mm=0.0, y_mm=0.0, *, sensor="poisson", rays=0,
         binning=_core.analysis_binning, splat="footprint", stratification=0, lens_model=None,
         photons_emitted=None, backend="vulkan", device=None, estimator="auto", converge=None,
         max_rays=_core.max_rays_converge, ambiguity=False, separation_mm=_core.min_separation_mm):
    """Cramer-Rao lower bounds of a point source's position, as `prism crlb`.

    scene: one scene (name, path, dict or Scene) or a list of them; the rows
        of each follow those of the one before.
    depth_mm, x_mm, y_mm: the source positions (depth from the scintillator
        face); scalars or arrays, broadcast against each other.
    sensor: "poisson" (the paper's eq. 2) or "binary" single-photon pixels.
{forward}
    estimator: the Fisher estimator, "auto" (split for point rays, naive for
        footprints), "split" or "naive", as the CLI's --fisher-estimator.
    converge: None: each row is checked against a quarter of the rays and
        flagged "moving" where its 3D CRLB changed by more than
        crlb_convergence_tol; a fraction (e.g. 0.02): the rays quadrupled up
        to max_rays until every 3D CRLB changes by at most it.
    ambiguity: also the global figure per row, as `prism crlb --ambiguity`:
        the closest impostor source at least separation_mm away on the binary
        sensor (alias_kl in nats at the row's photons, alias_*_mm its
        position) and p_confusion, the predicted probability per event that
        the estimate lands separation_mm or more away (ambiguity()).

    Returns a dict of arrays, one entry per row, named as the CSV columns of
    `prism crlb --csv`: scene, x_mm, y_mm, depth_mm, photons (expected
    detected), crlb_x_mm, crlb_y_mm, crlb_z_mm, crlb_3d_mm, lens_model,
    rays_per_lenslet, change_vs_quarter_rays (NaN where not measured), flag;
    with ambiguity also alias_kl, alias_x_mm, alias_y_mm, alias_depth_mm,
    p_confusion.
    """
    scenes = [globals()["scene"](s) for s in (scene if isinstance(scene, (list, tuple)) else [scene])]
    x, y, d = _np.broadcast_arrays(_np.asarray(x_mm, float), _np.asarray(y_mm, float), _np.asarray(depth_mm, float))
    positions = _np.ascontiguousarray(_np.stack([x.ravel(), y.ravel(), d.ravel()], axis=1))
    if positions.shape[0] == 0:
        raise ValueError("depth_mm: no positions given")
    if not _np.all(_np.isfinite(positions)):
        raise ValueError("x_mm, y_mm, depth_mm: every position must be finite")
    if converge is not None and not 0 < converge < 1:
        raise ValueError(f"converge: {converge} must lie in (0, 1)")
    if not separation_mm > 0:
        raise ValueError(f"separation_mm: {separation_mm} must be > 0")
    forward = _forward(rays, binning, splat, stratification, lens_model, photons_emitted, backend, device, estimator)
    out = _core.crlb(scenes, positions, forward, sensor, float(converge or 0), int(max_rays), bool(ambiguity),
                     float(separation_mm))
    for key in ("scene", "lens_model", "flag"):
        out[key] = _np.array(out[key], dtype=str)
    out["rays_per_lenslet"] = out["rays_per_lenslet"].astype(_np.int64)
    return out


def ambiguity(scene="prototype", depth_mm=25.0, x_mm=0.0, y_mm=0.0, *, photons=100.0,
              separation_mm=_core.min_separation_mm, binning=_core.analysis_binning, lens_model=None,
              backend="vulkan", device=None):
    """The global ambiguity of source positions at a given count of detected
    photons, as `prism evaluate --ambiguity` computes it for each event (crlb()
    gives it at the photons the scene's emission yields).

    depth_mm, x_mm, y_mm, photons: scalars or arrays, broadcast against each
        other; photons: expected detected photons of the source.
    separation_mm: the least distance of an impostor, and the error that
        p_confusion predicts (a catastrophic one).
    binning: the clicks' binning; the model is the scene's at it.
    lens_model, backend, device: as crlb().

    Returns a dict of arrays, one entry per position: alias_kl (nats),
    alias_x_mm, alias_y_mm, alias_depth_mm (the closest impostor) and
    p_confusion (the predicted probability per event that the estimate lands
    separation_mm or more away).
    """
    sc = globals()["scene"](scene)
    x, y, d, n = _np.broadcast_arrays(*(_np.asarray(v, float) for v in (x_mm, y_mm, depth_mm, photons)))
    positions = _np.ascontiguousarray(_np.stack([x.ravel(), y.ravel(), d.ravel()], axis=1))
    if positions.shape[0] == 0:
        raise ValueError("depth_mm: no positions given")
    if not _np.all(_np.isfinite(positions)):
        raise ValueError("x_mm, y_mm, depth_mm: every position must be finite")
    if not separation_mm > 0:
        raise ValueError(f"separation_mm: {separation_mm} must be > 0")
    forward = _forward(0, binning, "footprint", 0, lens_model, None, backend, device, "auto")
    return _core.ambiguity(sc, positions, _np.ascontiguousarray(n.ravel()), forward, float(separation_mm))


@_doc
def psf(scene="prototype", source_mm=(0.0, 0.0, 25.0), *, derivatives=False, rays=0, binning=1,
        splat="footprint", stratification=0, lens_model=None, photons_emitted=None, backend="vulkan", device=None):
    """The expected-photon image of a point source on the sensor, as
    `prism psf` (which writes it to OpenEXR).

    scene: a name, a JSON file's path, a dict or a Scene.
    source_mm: (x, y, depth) in mm, depth from the scintillator face.
    derivatives: also the image's derivatives by the source position.
{forward}

    Returns a float32 array of shape (rows, columns): expected photons per
    (binned) pixel, row 0 the sensor's first, pixels of the scene's sensor
    pixel times binning (6.9 um x binning for the built-ins). With
    derivatives, a dict: b and its derivatives db_dx, db_dy, db_ddepth (per
    mm), arrays that are views into one buffer, and pixel_mm.
    """
    sc = globals()["scene"](scene)
    x, y, d = (float(v) for v in source_mm)
    forward = _forward(rays, binning, splat, stratification, lens_model, photons_emitted, backend, device, "auto")
    image, pixel_mm = _core.psf(sc, x, y, d, forward, bool(derivatives))
    if not derivatives:
        return image[:, :, 0]
    return {"b": image[:, :, 0], "db_dx": image[:, :, 1], "db_dy": image[:, :, 2], "db_ddepth": image[:, :, 3],
            "pixel_mm": pixel_mm}


def set_max_memory(size):
    """Limit the memory work may plan to use, as bytes or with K, M, G, T
    (powers of 1024): "512M", "8G"; work estimated beyond it raises
    ResourceError before it starts. Default: 75% of this machine's memory,
    or $PRISM_MAX_MEMORY when set at import (as the command's --max-memory)."""
    _core.set_max_memory(str(size))


def max_memory_bytes():
    """The memory limit in bytes (set_max_memory)."""
    return _core.max_memory_bytes()


if _os.environ.get("PRISM_MAX_MEMORY"):
    set_max_memory(_os.environ["PRISM_MAX_MEMORY"])


def read_exr(path, channel="Y"):
    """One float channel of an OpenEXR file that prism wrote (a PSF, a
    dictionary tile) as a float32 array of shape (rows, columns)."""
    return _core.read_exr(str(path), channel)


# --- events -------------------------------------------------------------------

class Event(tuple):
    """One event: id, vertices (K, 5) float64 array of the truth (x_mm, y_mm,
    depth_mm, alpha: expected photons, sensor_fraction: the part of alpha that
    can reach the sensor), clicks: uint32 array of clicked pixels on the
    click grid, index row * grid_width + column, strictly increasing."""
    __slots__ = ()

    def __new__(cls, t):
        return tuple.__new__(cls, t)

    id = property(lambda self: self[0])
    vertices = property(lambda self: self[1])
    clicks = property(lambda self: self[2])

    def __repr__(self):
        return f"<prism.Event {self.id}: {len(self.vertices)} vertices, {len(self.clicks)} clicks>"


class EventFile:
    """An event file (host/events/EVENTS.md) read lazily: iterating reads one
    event at a time, so memory stays constant however long the file; each
    iteration starts from the first event. A truncated or corrupt file
    raises RuntimeError naming the file and the byte offset.

        f = prism.EventFile("out/events.events")
        for event in f:
            rows, cols = np.divmod(event.clicks, f.header["grid_width"])
    """

    def __init__(self, path):
        self.path = str(path)
        self.header = _core.EventReader(self.path).header()
        """dict: sensor_width_px, sensor_height_px, pixel_um, binning (clicks
        on binning x binning pixels), grid_width, grid_height, scene, truth
        (forward or dictionary), seed, provenance, event_count."""

    def __len__(self):
        return int(self.header["event_count"])

    def __iter__(self):
        reader = _core.EventReader(self.path)
        while True:
            e = reader.next()
            if e is None:
                return
            yield Event(e)

    def __repr__(self):
        return f"<prism.EventFile {self.path!r}: {len(self)} events of scene {self.header['scene']!r}>"


def simulate(scene="prototype", vertices=((1.0, 1.0, 31.0, 100.0),), events=1, *, seed=1, jitter_mm=0.0, out=None,
             truth="forward", dictionary=None, binning=None, rays=0, splat="footprint", stratification=0,
             device=None, progress=None):
    """Binary-sensor events (click lists), as `prism simulate`: the same
    (scene, vertices, seed, options) give the same events, event by event.

    scene: a name, a JSON file's path, a dict or a Scene.
    vertices: (K, 4) array-like of x_mm, y_mm, depth_mm, alpha (expected
        photons detected), the K vertices of every event; each must lie in
        the scene's volume.
    events: how many; event i depends only on (seed, i).
    jitter_mm: move each vertex uniformly within +-jitter_mm in x, y and
        depth, per event (each event then renders its own PSFs).
    out: None: return a list of Event; a path: write an event file there
        (written aside and renamed when whole) and return its header with
        event_count and bytes.
    truth: "forward" (the ray-traced model at the exact positions) or
        "dictionary" (the dictionary's PSFs shifted by the magnification rule,
        the paper's protocol; needs dictionary=DIR).
    binning: clicks on binning x binning sensor pixels; None: 1 (6.9 um) for
        the forward truth, the dictionary's base binning for its truth.
    rays, splat, stratification: the forward truth's sampling (0 rays: the
        splat's converged default), as in psf().
    device: the Vulkan device (forward truth).
    progress: None, or a callable progress(done, total) after each event.
    """
    sc = globals()["scene"](scene)
    v = _np.ascontiguousarray(_np.atleast_2d(_np.asarray(vertices, dtype=float)))
    if v.ndim != 2 or v.shape[1] != 4:
        raise ValueError(f"vertices: a (K, 4) array of x_mm, y_mm, depth_mm, alpha, not shape {v.shape}")
    if int(events) < 0:
        raise ValueError(f"events: {events} must be >= 0")
    if dictionary is not None and truth != "dictionary":
        raise ValueError("dictionary is read only with truth='dictionary' (the paper's protocol)")
    forward = _forward(rays, 1 if binning is None else binning, splat, stratification, None, None, "vulkan", device,
                       "auto")
    if binning is None and truth == "dictionary":
        forward["binning"] = 0  # the dictionary's base
    result = _core.simulate(sc, v, int(events), int(seed), float(jitter_mm), forward, str(truth),
                            str(dictionary or ""), str(out or ""), progress)
    return result if out else [Event(e) for e in result]


# --- dictionaries ---------------------------------------------------------------

class Dictionary:
    """A PSF dictionary on disk (docs/dictionary.md), opened and its
    manifest checked.

    Entry i is the PSF of a source at positions[i] (x varies fastest, then
    y, then depth); level 0 is the sensor binned base_binning x base_binning,
    level k sums 2^k x 2^k level-0 pixels; every level of a PSF sums to 1
    over the sensor (probabilities, not photons).
    """

    def __init__(self, path):
        self.path = str(path)
        self._r = _core.DictionaryReader(self.path)
        self.manifest = _json.loads(self._r.manifest_json())
        """dict: the manifest as stored (scene, grid, levels, base_binning, ...)."""
        self.scene = self._r.scene()
        self.positions = self._r.positions()
        """(N, 3) array of each entry's source x_mm, y_mm, depth_mm."""
        self.grid_x_mm, self.grid_y_mm, self.grid_depth_mm = (_np.array(a) for a in self._r.grid())
        self.levels = self._r.levels()
        self.base_binning = self._r.base_binning()

    def __len__(self):
        return self._r.size()

    def present(self):
        """How many entries are on disk (a build stopped early has fewer)."""
        return self._r.present()

    def pixel_mm(self, level=0):
        """The pixel pitch of a level in mm."""
        return self._r.pixel_mm(int(level))

    def level_shape(self, level=0):
        """(rows, columns) of a level."""
        return self._r.level_shape(int(level))

    def index(self, x_mm, y_mm, depth_mm):
        """The entry whose source lies nearest (x_mm, y_mm, depth_mm), axis by
        axis."""
        ix = int(_np.argmin(_np.abs(self.grid_x_mm - x_mm)))
        iy = int(_np.argmin(_np.abs(self.grid_y_mm - y_mm)))
        iz = int(_np.argmin(_np.abs(self.grid_depth_mm - depth_mm)))
        return ix + len(self.grid_x_mm) * (iy + len(self.grid_y_mm) * iz)

    def psf(self, index, level=0, window=None):
        """Entry `index` at `level` as a float32 array (rows, columns) of
        probabilities; with window=(x0, y0, width, height) only those pixels
        (cropped to the level), read tile by tile."""
        self._check(index, level)
        if window is None:
            return self._r.read_level(int(index), int(level))
        x0, y0, w, h = (int(v) for v in window)
        if w <= 0 or h <= 0:
            raise ValueError(f"window: width and height must be > 0, not {w} x {h}")
        return self._r.read_window(int(index), int(level), x0, y0, w, h)[0]

    def _check(self, index, level):
        if not 0 <= int(index) < len(self):
            raise IndexError(f"index {index}: the dictionary has entries 0..{len(self) - 1}")
        if not 0 <= int(level) < self.levels:
            raise ValueError(f"level {level}: the dictionary has levels 0..{self.levels - 1}")
        if not self._r.has(int(index)):
            raise RuntimeError(f"{self._r.path_of(int(index))}: entry {index} is not on disk (a build stopped before "
                               "it; run the build again to finish it)")

    def __repr__(self):
        return (f"<prism.Dictionary {self.path!r}: {len(self)} PSFs of scene {self.scene.name!r}, "
                f"{self.present()} present, {self.levels} levels from {self.pixel_mm(0) * 1e3:.1f} um>")


def build_dictionary(out, scene="prototype", *, grid_x_mm=None, grid_y_mm=None, grid_depth_mm=None, binning=4,
                     rays=4096, splat="footprint", stratification=0, device=None, progress=None):
    """Synthesise a PSF dictionary with the forward model, as `prism
    dictionary build`, and return it opened (a Dictionary).

    out: the dictionary's folder. Resumable: entries already there are kept,
        so a stopped build continues where it stopped.
    grid_x_mm, grid_y_mm, grid_depth_mm: the source positions of the grid
        (each strictly increasing); None: the default, the paper's x and y
        nodes (-25..25 mm in steps of 5) and depth planes dense near the face
        (2783 PSFs).
    binning: level 0 is the sensor binned binning x binning (4: 27.6 um).
    rays, splat, stratification: the forward model's sampling, as in psf().
    progress: None, or a callable progress(done, total) after each PSF.

    Returns the Dictionary; its build report (rendered, reused, seconds,
    seconds_per_psf) is its attribute `report`.
    """
    sc = globals()["scene"](scene)

    def axis(values):
        return [] if values is None else [float(v) for v in _np.atleast_1d(values)]

    report = _core.build_dictionary(sc, str(out), axis(grid_x_mm), axis(grid_y_mm), axis(grid_depth_mm),
                                    int(binning), int(rays), str(splat), int(stratification), device or "", progress)
    d = Dictionary(out)
    d.report = report
    return d


# --- reconstruction ---------------------------------------------------------------

def reconstruct(dictionary, events, *, vertices=1, binning=None, model=None, scene=None, backend="vulkan",
                device=None, precision="float", level=None, scan_step=1, carry_margin=None, tau_mm=None,
                dark_rate=None, search_dark_rate=None, batch=None, serial_scans=False, budget_mib=1024.0, threads=None,
                progress=None):
    """The vertices of every event, as `prism reconstruct` (the paper's
    ADCG-inspired search on the sparse likelihood, then the continuous
    maximum-likelihood refinement; docs/reconstruction.md).

    dictionary: a dictionary's folder (or a Dictionary).
    events: an event file's path (read a batch at a time: constant memory),
        an EventFile, or a sequence of events (prism.Event or (id, vertices,
        clicks) with vertices None when there is no truth).
    vertices: K, the vertices per event (1..8).
    binning: for a sequence of events, the binning of their click grid;
        None: the dictionary's base binning. (A file says its own.)
    model: the continuous refinement: "scene" (the scene's forward model,
        the default for synthesised dictionaries), "dictionary" (its PSFs
        interpolated, the default for calibrated ones) or "none" (the
        search's grid positions alone).
    scene: a scene (name or JSON file) for model="scene" instead of the one
        the dictionary was built from.
    backend: "vulkan" (sparse scan on the device), "dense" (the paper's dense
        correlation on the device) or "cpu" (the double reference).
    device, precision ("float" or "half": the scan level's values on the
        device), level (the scan level; None: chosen by a budget of shifts
        per click), scan_step, carry_margin, tau_mm, dark_rate,
        search_dark_rate (per sensor pixel; 0: dark_rate alone), batch (events per
        device scan), serial_scans, budget_mib, threads (host threads; None: 1 for the cpu backend, this
        machine's hardware threads up to 8 for the device ones): as the
        command's options of the same names.
    progress: None, or a callable progress(done, total) as events are done
        (it must not call prism itself).

    Returns a dict of arrays, one entry per vertex, named as the command's
    CSV columns: event, vertex, x_mm, y_mm, depth_mm, alpha, nll, clicks,
    flags, crlb_x_mm, crlb_y_mm, crlb_z_mm, crlb_3d_mm, fit_pvalue (the last
    five NaN without refinement).
    """
    d = _core.reconstruction_defaults()
    options = dict(backend=str(backend), precision=str(precision), model="" if model is None else str(model),
                   scene="" if scene is None else str(scene), batch=int(batch or d["batch"]),
                   level=-1 if level is None else int(level),
                   budget_mib=float(budget_mib), threads=0 if threads is None else int(threads), serial_scans=bool(serial_scans),
                   vertices=int(vertices), scan_step=int(scan_step),
                   carry_margin=float(d["carry_margin"] if carry_margin is None else carry_margin),
                   tau_mm=float(d["tau_mm"] if tau_mm is None else tau_mm),
                   dark_rate=float(d["dark_rate"] if dark_rate is None else dark_rate),
                   search_dark_rate=float(d["search_dark_rate"] if search_dark_rate is None else search_dark_rate))
    if not options["dark_rate"] > 0:
        raise ValueError(f"dark_rate: {dark_rate} must be > 0 (expected counts per click pixel)")
    if not options["search_dark_rate"] >= 0:
        raise ValueError(f"search_dark_rate: {search_dark_rate} must be >= 0 (expected counts per sensor pixel)")
    if not 1 <= options["vertices"] <= 8:
        raise ValueError(f"vertices: {vertices} is not in 1..8")
    if not 1 <= options["batch"] <= 65535:
        raise ValueError(f"batch: {batch} is not in 1..65535")
    if threads is not None and not 1 <= options["threads"] <= 256:
        raise ValueError(f"threads: {threads} is not in 1..256 (None: 1 for the cpu backend, the hardware threads up to 8 for the device ones)")
    if options["model"] not in ("", "scene", "dictionary", "none"):
        raise ValueError(f"model {model!r}: use 'scene', 'dictionary' or 'none'")
    if isinstance(dictionary, Dictionary):
        dictionary = dictionary.path
    if isinstance(events, EventFile):
        events = events.path
    source = str(events) if isinstance(events, (str, _os.PathLike)) else list(events)
    table = _core.reconstruct(str(dictionary), source, int(binning or 0), options, device or "", progress)
    table["flags"] = _np.array(table["flags"], dtype=str)
    return table
