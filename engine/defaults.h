// Physics constants and defaults of the PRISM prototype, in one place, with
// units in the names. Sources: ../shared/DESIGN.md ("Geometry and defaults")
// and the paper (Sec. II, III.A). Where DESIGN.md fixes what the paper leaves
// open (lenslet arrangement, centre thickness), the comment says so.
#pragma once

namespace prism::defaults {

// Geometry (z along the optical axis, lens plane at z = 0).
inline constexpr double lens_to_sensor_mm = 18.5;   // lens plane to sensor
inline constexpr double working_distance_mm = 5.0;  // lens plane to scintillator face
inline constexpr double volume_half_width_mm = 25.0;  // x, y in [-25, 25]
inline constexpr double volume_depth_mm = 50.0;       // depth in [0, 50] from the face

// Sensor: SVS-SHR661 with 2x2 binning (3.45 um native pixels).
inline constexpr int sensor_width_px = 6696;
inline constexpr int sensor_height_px = 4764;
inline constexpr double pixel_um = 6.9;

// Lenslets: 3 mm plano-convex N-BK7, seven focal lengths, six of each.
inline constexpr double lenslet_diameter_mm = 3.0;
inline constexpr double focal_lengths_mm[7] = {3.0, 4.5, 6.0, 7.5, 9.0, 12.0, 15.0};
inline constexpr double glass_index_nbk7 = 1.5168;  // at 587.6 nm (LED at 570 nm)
inline constexpr double edge_thickness_mm = 0.5;    // DESIGN.md: centre thickness = rim sag + 0.5 mm
// Arrangement (DESIGN.md; the paper's figure is lost): 6 rows x 7 columns,
// hex packed, focal index (column + 3 row) mod 7, centroid on the axis.
inline constexpr int lenslet_rows = 6;
inline constexpr int lenslet_columns = 7;
inline constexpr double lenslet_pitch_mm = 4.0;
// As built (calibration): the largest tilt of a lenslet or of the sensor a
// scene may give. Mounting errors are a degree or so; beyond 10 degrees a
// tilted lens would cut into its neighbours and the holder.
inline constexpr double max_tilt_deg = 10.0;

// Source: the paper's isotropic emitter (Sec. II.C).
inline constexpr double photons_emitted = 6280.0;
// The most a scene or --photons may give: far above any event (a GeV
// deposited in a bright scintillator emits ~1e7), and low enough that the
// device's float expected counts and Fisher sums stay finite (1e300 gave inf).
inline constexpr double max_photons_emitted = 1e12;

// Effects, when a scene names them without parameters.
inline constexpr double scintillator_index = 1.58;   // plastic scintillator (PVT)
inline constexpr double holder_bore_mm = 2.0;        // bore behind the lens plane
inline constexpr double detection_efficiency = 1.0;  // fill factor x PDE
inline constexpr double dark_counts_per_pixel = 0.0; // expected dark counts per pixel per event
inline constexpr double source_sigma_mm = 0.3;       // Gaussian source extent, per axis (LED die ~0.5 mm)
inline constexpr double wavelength_nm = 570.0;       // effect diffraction: the calibration LED (DESIGN.md)
// Effect diffraction: the Airy core's width as the sigma of its Gaussian
// fit, sigma = airy_gaussian_factor * lambda * L / D (L: lens to sensor, D:
// lenslet diameter; Zhang, Zerubia & Olivo-Marin, Appl. Opt. 46 (2007):
// 0.21 lambda / NA). The kernels spread light over a uniform square of the
// same variance, half side sqrt(3) sigma (shaders/common/blur.glsl says why).
inline constexpr double airy_gaussian_factor = 0.42;
inline constexpr double airy_square_half_side_per_sigma = 1.7320508075688772;  // sqrt(3)

// Analysis defaults, chosen by the convergence study (docs/model.md "Convergence";
// bench/bench_forward, six positions of the prototype). Footprint splat (box
// pixels, the default) at 16384 cells per 3 mm lenslet: thin lenses within
// 0.3% of the exact box-pixel oracle at 110, 27.6 and 6.9 um; real lenses
// within 0.5% of 16x the cells at 110 um, but 4.5% at 27.6 um (65536 cells:
// 0.7%) and 8.5% at 6.9 um. `prism crlb` therefore checks every row against a
// quarter of the cells and flags those that moved by more than
// crlb_convergence_tol. The point splat (the paper's bilinear rays) needs
// 65536 rays at 110 um with the split estimator and does not converge at
// 27.6 um or below.
inline constexpr unsigned rays_per_lenslet = 16384;        // footprint cells: 128 x 128 strata
inline constexpr unsigned rays_per_lenslet_point = 65536;  // point rays: 256 x 256 strata
inline constexpr unsigned analysis_binning = 16;           // 110.4 um analysis pixels
// Design sweeps rank designs, which needs fewer cells than a converged CRLB:
// bench/bench_sweep (8 designs, 54 samples, 221 um pixels) found the
// footprint's ranking at 256, 1024 and 4096 cells identical to 16384's
// (Kendall tau 1.0; scores within 0.6%, 0.3%, 0.1%), the point splat's at
// 4096 rays tau 0.32 (and singular samples below that).
inline constexpr unsigned sweep_rays_per_lenslet = 1024;        // footprint cells: 32 x 32 strata
inline constexpr unsigned sweep_rays_per_lenslet_point = 4096;  // point rays
inline constexpr unsigned sweep_binning = 32;                   // 221 um analysis pixels
inline constexpr double crlb_convergence_tol = 0.01;       // relative change of the 3D CRLB over 4x the rays (cells)
// Analysis pixels finer than this see the real lenses' caustics: their
// geometric CRLB need not settle with the cells (27.6 um: 4.5% between 16384
// and 65536; 110 um: 0.5%; docs/model.md "Convergence"), and `prism crlb` says so.
inline constexpr double caustic_pixel_mm = 0.06;

// Dictionary grid (prism dictionary build): lateral nodes every 5 mm over
// the volume, as the paper's 11 x 11. Depth planes: the paper's 5 mm steps
// from 5 to 50 mm leave the first 5 mm empty and are too coarse near the
// face, where the PSF changes fastest with depth (the lenslet images lie
// pitch x (1 + L / D) apart, D = depth + working distance, and their blur
// grows like 1 / D). Planes every 1 mm to 12 mm, 1.5-2.5 mm to 20 mm, then
// 5 mm: on 40 thin-lens events at depth 2..12 mm with the refinement the
// catastrophic rate fell from 60% (5 mm planes) to 10% (docs/reconstruction.md "Accuracy").
inline constexpr double dictionary_depth_planes_mm[] = {0,  1,  2,  3,  4,    5,  6,    7,  8,  9,  10, 11,
                                                        12, 13.5, 15, 17.5, 20, 25, 30, 35, 40, 45, 50};

// The support scan's default level (host/reconstruct/reconstruct.h,
// default_search_level): the finest whose shifts over all PSFs, per click of
// an event, stay within this. The default 2783-PSF dictionary at 110 um
// clicks holds 1.03e6 / 2.75e5 / 8.3e4 / 3.0e4 on levels 2..5 (radius
// tau * magnification rounded to the nearest pixel, the lattice of every
// shift place() can give). On 1000 volume events level 4 took a seventh to
// a tenth of level 2's time (two series) with the same catastrophic count
// and median error; coarser, the scan gains little and more PSFs must be
// carried down (docs/reconstruction.md, "The scan's lattice"). The
// 1210-PSF paper grid holds 1.32e5 / 3.8e4 on levels 2 / 3 and gets level 3
// (level 2 was 3.2-3.3x slower there, 113 against 108 events beyond 3 mm).
inline constexpr double search_shifts_per_click = 1.0e5;
// Coarse to fine (host/reconstruct/reconstruct.h, select_level): the PSFs
// carried from a coarse scan are ranked again on pixels of this many sensor
// pixels per axis (441.6 um on the prototype's 6.9 um sensor), or on the
// clicks' level + 2 where that is coarser. The PSFs within the carry margin
// (up to 512) go down to it one level at a time, each through the tiles
// around its clicks, before the best 8 go on to the clicks: at 6.9 um clicks
// the clicks' level + 2 (27.6 um) cost five levels of tiles for each (docs/reconstruction.md
// "Clicks at the sensor's own pixels").
inline constexpr int select_pixel_sensor_px = 64;
// The refine_candidates PSFs ranked at the select level go down to the
// finest level whose pixels span at least this many sensor pixels per axis
// (the clicks' level where that is coarser) and are ranked by their NLL
// there; only the best goes on to the clicks. At 110 um clicks (16 sensor
// pixels) that is the clicks' level, as before; at 6.9 um clicks it is 27.6
// um, which spares seven of the eight the two finest levels of tiles (docs/reconstruction.md
// "Clicks at the sensor's own pixels").
inline constexpr int rank_pixel_sensor_px = 4;
// Device backends scan a pass's events this many at a time (one dispatch
// per dictionary chunk), the host descending each chunk while the device
// scans the next (host/reconstruct/reconstruct.h); `prism reconstruct`
// hands the search scan_chunks_per_batch such chunks at once.
inline constexpr int scan_chunk_events = 64;
inline constexpr int scan_chunks_per_batch = 4;
// The search's likelihood floor (ReconstructionSettings::search_dark_rate),
// expected counts per sensor pixel and event: 1e-4 per 110 um click pixel
// (16 x 16 sensor pixels). Of 1e-6..1e-3 per 110 um pixel on 1000 volume
// events (seed 7), and checked on 1000 others (seed 8): docs/reconstruction.md "The floor
// with the refinement". At the sensor's own pixels it is below the weights'
// dark rate, which the search then keeps.
inline constexpr double search_dark_rate_per_sensor_pixel = 1e-4 / 256;

// Continuous refinement of reconstructed vertices (host/reconstruct/refine.h):
// the scene's forward model, footprint splat, at this many cells per lenslet
// (1% L1 from 16384 cells on the prototype at 110 um; docs/reconstruction.md).
inline constexpr unsigned refine_rays_per_lenslet = 1024;
// The refinement renders on pixels of at least this many sensor pixels per
// axis (110.4 um on the prototype's 6.9 um sensor); finer clicks are binned
// to them for it, and its answer is then fitted locally on the clicks' own
// pixels (host/reconstruct/refine.h, Refinement; docs/reconstruction.md "Refinement at the
// sensor's own pixels": a render at 6.9 um costs 50-100 times one at 110 um).
inline constexpr int refine_pixel_sensor_px = 16;
// The polish on the clicks' own pixels (Refinement) starts where the
// refinement on coarser pixels ended, a fraction of such a pixel from the
// clicks' optimum, across the sharp images' cliffs; it also fits through the
// images blurred by these Gaussian sigmas, in pixels of the coarser level,
// then sharp, and keeps the lower NLL (on the thin-lens row of the tests, one
// event in four stopped 4 CRLB off without it).
inline constexpr double refine_polish_blur_refine_px[] = {0.5, 0.125};
inline constexpr int refine_iterations = 20;       // Levenberg-Marquardt steps per start, at most
inline constexpr int refine_search_starts = 3;     // the search's runners-up probed per vertex
inline constexpr int refine_alias_starts = 2;      // lattice aliases probed per vertex
// A fit flagged poor (p < fit_pvalue_flag) after every start also tries the
// aliases of its estimate for lattice vectors up to this many pitches (18 in
// the hex array): near the face the search confuses sources two pitches apart.
inline constexpr double refine_rescue_alias_pitches = 2.0;
// A fit this poor or worse (p-value) also scans the lattice that its clicks
// vote for (host/reconstruct/click_geometry.h): every alias site of the best
// voted position, one render each. Near the face a wrong fit of the real
// lenses' prototype scored p 0.001-0.034 with an NLL ~270 above the truth's;
// ordinary events fall below it at most 5% of the time (the p-value is
// conservative): 6 of 500 thin-lens and 0 of 60 real-lens volume events.
inline constexpr double refine_lattice_scan_pvalue = 0.05;
// An estimate shallower than this, or an event with fewer clicks than the
// next, gets the lattice scan whatever its fit, its sites scored and first
// fitted blurred, and the continuation.
// Near the face a source put on a wrong site 2-4 pitches away fits as well
// as the model expects (p 0.14-0.79 in the volume runs of 500 thin-lens and
// 355 real-lens events at 100 photons), and there the images are sharpest,
// so the cliffs that their hard edges make in the likelihood hold a local
// fit several CRLBs off.
inline constexpr double refine_always_scan_below_mm = 10.0;
// With few clicks the same holds at every depth. At 20 photons (about 17
// clicks) 6 of unifocal-f15's 7 estimates beyond 3 mm over 80 events, at
// depths 11-34 mm, lay where the likelihood has a better optimum by the
// truth (12-43 nats lower; evaluate's truth fit), most a lattice pitch
// over, with p 0.16-0.54: the first fit from the search had stopped 0.5 mm
// from that optimum at a cliff. With the scan and the continuation at every
// depth 5 of the 6 were found. At 50 photons (about 43 clicks) no deep
// search failure was seen (unifocal-f9, 300 events; unifocal-f15, 30), and
// at 100 photons deeper than 10 mm the scan changed no estimate by a CRLB
// for 3.1x the renders (12 prototype events: median 285 against 90). So
// events with fewer clicks than this get it; between 17 and 43 clicks the
// need is not measured (docs/reconstruction.md).
inline constexpr int refine_always_scan_below_clicks = 30;
inline constexpr int refine_lattice_scan_depths = 3;  // the best voted depths tried, while the fit stays below it and improves
// The ladder: after the other starts, points every 0.75 mm up to 3 mm along
// the estimate's weakest direction and along depth, the best 2 probed. On 60
// events over the prototype's volume 9 ended 1-2.4 mm off in a local optimum
// along that direction, with the truth's basin the better one (docs/reconstruction.md).
inline constexpr int refine_ladder_starts = 2;
inline constexpr int refine_ladder_rungs = 4;          // per side and direction
inline constexpr double refine_ladder_step_mm = 0.75;
// Each rung's image is also scored moved by up to this many click-grid pixels
// (the source moved laterally to match): near the face a rung 0.75 mm off in
// depth images a few pixels away from the source's, and unmoved it scores as
// badly as a wrong one. Of the 345 first events of the real-lens acceptance
// run, three ended 0.4-0.8 mm off with the truth's basin 17-71 lower in NLL;
// with 2 pixels all three reach it.
inline constexpr int refine_ladder_reach_px = 2;
// The continuation after the last start, near the face: the estimate
// refitted with the model's images blurred by these Gaussian sigmas
// (click-grid pixels) in turn, then sharp, and kept if better
// (host/reconstruct/refine.cpp).
inline constexpr double refine_continuation_blur_px[] = {1.0, 0.5};
inline constexpr double refine_blur_radius_sigmas = 2.5;  // the blur kernel's half-width
// The lattice scan's sites near the face are scored, and fitted first, with
// the model's images blurred by this Gaussian sigma (click-grid pixels, as
// the continuation's): there the search's wrong answer is an alias of the
// source at another depth, from which the source's own site lies a tenth of
// a mm or two off, and sharp images score that as badly as any wrong site.
// In an event at depth 1 mm (110 um clicks) 4 pixels widened the truth's
// basin from about 0.25 mm to 0.3-0.4 mm of source position.
inline constexpr double refine_site_blur_px = 4.0;
inline constexpr int fit_pvalue_draws = 1000;      // Monte Carlo events per goodness-of-fit p-value
inline constexpr double fit_pvalue_flag = 0.01;    // below it a vertex is flagged poor_fit

// Accuracy figures (prism evaluate): an estimate more than this far from the
// truth in 3D is catastrophic (a wrong alias or plane, not a noisy fit); it is
// counted as a rate and left out of the per-axis RMSE.
inline constexpr double catastrophic_error_mm = 3.0;

// Calibration (prism calibrate, host/calibrate/calibrate.h): a measured PSF's
// pixel has the variance of an HDR merge, which grows with its signal (shot
// noise) above a floor (read noise, the merge's rejected faint pixels). The
// fit weighs pixel i of a PSF by 1 / (p_i + floor), the floor this fraction
// of the PSF's brightest pixel: the faintest pixels a 12-bit merge keeps
// over the paper's 7 exposures lie about 1e-4 below the peak.
inline constexpr double calibration_weight_floor = 1e-4;
// A measured PSF's pixels fainter than this times the faintest value its HDR
// merge kept are left out of the fit: near the merge's threshold a pixel is
// kept only when noise pushed it up, and rejected ones read 0
// (host/calibrate/calibrate.cpp, Noise). Ten times the threshold is where a
// 12-bit merge's relative noise falls to a few per cent.
inline constexpr double calibration_reliable_over_faintest = 10.0;
// The model's pixels: the finest level of the dictionary at least this
// coarse (the design studies' 110 um; calibrate --level chooses another).
inline constexpr double calibration_pixel_um = 110.0;
// The model's footprint cells per lenslet: the refinement's. On the
// synthetic as-built test the sandwich alone leaves the f = 3 mm near
// hemisphere's lenslet 6-10 sigma off at 1024 (its images are the largest
// and most curved); with the cells' term (below) every parameter lies within
// 3 sigma (docs/calibration.md).
inline constexpr unsigned calibration_rays_per_lenslet = 1024;
// After the fit, the model is evaluated again with this many times its cells
// (one Gauss-Newton step, calibrate.h): how far that moves each parameter is
// its uncertainty from the model's cells, added to the fit's. 1: no check.
// The step is the model's own error less the finer model's, which is 1/2 of
// it at 4x the cells (noise-like, 1 / sqrt(cells)) and 1/4 at 16x; at 110 um
// pixels the check's time grows slowly with the cells (the whole prototype:
// 54-75 s at 16x, 39-56 s at 4x). At 4x the f = 3 mm lenslets' cell error came out
// too small: the synthetic row's f = 3 mm position sigma 7 um at 4x, 10.6 um
// at 16x for an error of 15 um; the whole prototype 207 of 216 parameters
// within 3 sigma at 4x, 211 at 16x (docs/calibration.md).
inline constexpr unsigned calibration_cells_check_factor = 16;
// A bootstrap replicate (calibrate --bootstrap) starts at the fit's end and
// takes at most this many steps on the model's pixels: on the whole
// prototype's 24 HDR PSFs the first two steps of a replicate gained 1.4e-3 to
// 4.3e-3 of its chi2, steps 3 to 6 at most 6e-5 (10 replicates,
// results/calibration-volume/bootstrap).
inline constexpr int calibration_bootstrap_steps = 6;
inline constexpr int calibration_max_steps = 40;  // Levenberg-Marquardt steps accepted at most, per level
// The fit runs first on pixels 2^k times larger, k from this down to 1, then
// on the model's: the disc edges make chi2 a staircase at the pixel scale,
// and a start whose images are more than a pixel off lies outside the basin.
inline constexpr int calibration_coarse_levels = 2;
// How far a parameter may move from the nominal scene: mounting and
// manufacturing tolerances are tens of um, a few % of focal length and a
// few tenths of a mm of spacing; these bounds are 10x wider, and keep every
// trial scene one the model can trace.
inline constexpr double calibration_max_shift_mm = 0.5;     // lens and sensor positions
inline constexpr double calibration_max_focal_change = 0.2; // relative
inline constexpr double calibration_max_distance_mm = 2.0;  // lens-to-sensor and working distance
// The blur term's range (effect source_extent's sigma, per axis): from just
// above 0 (where the blurred image no longer moves with sigma) to a source
// several mm across, far beyond an LED die (source_sigma_mm above).
inline constexpr double calibration_min_source_sigma_mm = 0.005;
inline constexpr double calibration_max_source_sigma_mm = 2.0;
// The blur term blurs each lenslet's image rendered on pixels this many
// times finer than the model's (calibrate --blur-supersample). A source of
// 0.25 mm blurs a deep, sharp image by about one 110 um pixel, and the 110
// um image does not say where within its pixel the light lies. On three
// lenslets finer pixels gained little (sigma 1.8% and 1.7% high, 6 and 9 of
// 22 parameters within 3 sigma at 1 and 4) for 34x the time (docs/calibration.md, the blur term).
inline constexpr unsigned calibration_blur_supersample = 1;

}  // namespace prism::defaults
