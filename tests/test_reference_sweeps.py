"""The stored pymust sweeps (``benchmarks/reference/sweeps.npz``): consistent with the scene
``benchmarks/reference_sweeps.py`` defines today, and localized by the refined method as
well as sim_us's frames of the same scene are: the first check of the localizer on frames
sim_us did not draw.

The file is written by ``python benchmarks/reference_sweeps.py --write`` with pymust;
these tests read it without pymust.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from calib import se3
from calib.image import us_to_pixel
from sim_us.beam import flat_echo_gain

from .benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
MM = 1e-3


RS = load_benchmark("reference_sweeps")


@pytest.fixture(
    scope="module",
    params=[s for s in RS.SURFACES if RS.stored_path(s).exists() or s == "smooth"],
)
def data(request) -> dict:
    """A surface's stored sweeps (the smooth sphere's are always there; the diffuse one's
    when rendered)."""
    return RS.load_stored(request.param)


def test_the_file_says_where_it_comes_from(data):
    meta = data["meta"]
    surface = data["surface"]
    assert meta["command"] == RS.command(surface)
    assert meta["pymust_version"]
    method = dict(meta["method"])
    # Frames rendered before the display's 0 dB moved to the elevation focus were shown
    # again with it (write_zero_db), which the record says.
    regreyed = method.pop("regreyed", None)
    assert regreyed is None or "write_zero_db" in regreyed
    assert method == RS.method_record(surface)
    assert meta["array"] == asdict(RS.PR.paper_probe().array)
    probe = RS.probe_config()
    for key, value in meta["probe"].items():
        np.testing.assert_allclose(value, getattr(probe, key), err_msg=key)
    assert [tuple(s.values()) for s in meta["sweeps"]] == [
        (s.lateral_mm, s.depth_mm, s.elevation_mm, list(s.rotation_deg)) for s in RS.SWEEPS
    ]
    assert RS.stored_path(surface).stat().st_size <= 3e6


def test_the_frames_0_db_is_sim_us_s(data):
    """The frames' 0 dB is pymust's perfect reflector at the elevation focus as displayed
    (sim_us's 0 dB), and pymust's perfect reflector at each cap's depth against it agrees
    with sim_us's flat reflector against depth (``flat_echo_gain``, same imaging) within
    1 dB: −7.4 / −1.0 / −0.5 dB against −7.1 / −1.3 / −0.3 dB at 10 / 15 / 20 mm. Before,
    pymust's frames were shown with the cap's depth as 0 dB, 7.4 dB brighter than sim_us's
    at the shallowest sweep."""
    probe = RS.probe_config()
    shown = 1.0 / float(data["axial_scale"])
    for i, info in enumerate(data["meta"]["per_sweep"]):
        cap_depth = (data["centre_ref"][i][1] - RS.RADIUS_M) * shown
        pymust_db = 20 * np.log10(info["reference_envelope"] / info["zero_db_envelope"])
        twin_db = 20 * np.log10(float(flat_echo_gain(probe, cap_depth, RS.WATER_C)))
        assert abs(pymust_db - twin_db) <= 1.0, (i, pymust_db, twin_db)


def test_regreyed_frames_move_lit_levels_only():
    """Shown again with a stronger 0 dB, every lit grey level moves down by the ratio in
    dB (rounded), levels that fall below black become black, black stays black, and a
    weaker 0 dB is refused (the pixels it would light were clipped black)."""
    frames = np.array([[0, 1, 40, 200, 255]], np.uint8)
    out = RS.regreyed(frames, 1.0, 10 ** (6.0 / 20), 60.0)  # 6 dB darker: 25.5 grey
    np.testing.assert_array_equal(out, [[0, 0, 15, 175, 230]])
    np.testing.assert_array_equal(RS.regreyed(frames, 2.0, 2.0, 60.0), frames)
    with pytest.raises(ValueError):
        RS.regreyed(frames, 2.0, 1.0, 60.0)


def test_frames_poses_and_truth_are_consistent(data):
    """uint8 frames of sim_us's image size and spacing; poses that are today's sweeps
    (a linear sweep along each frame's own z, the protocol's 21 frames 1 mm apart); the
    true centre where the poses put the sphere; axial scale c_water / 1540."""
    probe = RS.probe_config()
    frames = data["frames"]
    assert frames.dtype == np.uint8
    assert frames.shape == (len(RS.SWEEPS), RS.FRAMES, *probe.image_shape)
    np.testing.assert_allclose(data["spacing"], probe.spacing_m)
    np.testing.assert_allclose(data["axial_scale"], RS.WATER_C / 1540.0)
    assert float(data["radius"]) == RS.RADIUS_M
    np.testing.assert_array_equal(data["T_ee_us"], np.eye(4))
    for i, spec in enumerate(RS.SWEEPS):
        T = data["T_base_ee"][i]
        se3.check(T, "T_base_ee", batch=True)
        np.testing.assert_allclose(T, RS.sweep_poses(spec), atol=1e-12)
        step = T[0, :3, 2] * RS.FRAME_STEP_M
        np.testing.assert_allclose(np.diff(T[:, :3, 3], axis=0), np.tile(step, (RS.FRAMES - 1, 1)))
        np.testing.assert_allclose(T[:, :3, :3], np.broadcast_to(T[0, :3, :3], (RS.FRAMES, 3, 3)))
        centre = data["centre_ref"][i]
        middle = T[RS.FRAMES // 2]
        np.testing.assert_allclose(centre, se3.apply(se3.invert(middle), data["centre_base"]))
        np.testing.assert_allclose(
            centre / MM, [spec.lateral_mm, spec.depth_mm, spec.elevation_mm], atol=1e-9
        )


def test_the_cap_is_drawn_where_the_sphere_is(data):
    """In the frame nearest the sphere's centre, the echo within 6 dB of its peak is
    centred (grey-weighted) on the cap's top: its displayed depth and the sphere's
    column, within 0.1 mm (the brightest pixel itself may lie anywhere along the cap's
    flat top: the steered waves' specular points sit ± R sin 4° apart); the brightest
    frame is within one of it, the sweep's ends are black (the sphere beyond the
    elevation reach), and nothing is drawn outside the beamformed crop."""
    H, W = data["frames"].shape[2:]
    spacing = tuple(data["spacing"])
    shown = 1.0 / float(data["axial_scale"])
    for i, info in enumerate(data["meta"]["per_sweep"]):
        frames = data["frames"][i]
        c = data["centre_ref"][i]
        k = RS.FRAMES // 2 + round(c[2] / RS.FRAME_STEP_M)
        f = frames[k].astype(float)
        top_6db = np.where(f >= f.max() - 6.0 * 255.0 / RS.probe_config().dynamic_range_db, f, 0.0)
        rows, cols = np.mgrid[0:H, 0:W]
        r = (top_6db * rows).sum() / top_6db.sum()
        col = (top_6db * cols).sum() / top_6db.sum()
        top = np.array([c[0], (c[1] - RS.RADIUS_M) * shown, 0.0])
        r_true, c_true = us_to_pixel(top, W, spacing)
        assert abs(r - r_true) * spacing[1] < 0.1 * MM
        assert abs(col - c_true) * spacing[0] < 0.1 * MM
        peaks = frames.reshape(len(frames), -1).max(axis=1)
        assert abs(int(np.argmax(peaks)) - k) <= 1 and peaks[0] == peaks[-1] == 0
        r0, r1 = info["crop_rows"]
        c0, c1 = info["crop_cols"]
        outside = frames.copy()
        outside[:, r0 : r1 + 1, c0 : c1 + 1] = 0
        assert not outside.any()


def _errors(data: dict, method: str) -> tuple[list, list, np.ndarray, np.ndarray]:
    """The localizer on pymust's sweeps and on sim_us's frames of the same scene: the
    results and their errors (mm, NaN where rejected)."""
    truths = data["centre_ref"]
    ref = RS.localize(RS.sweeps_of(data["frames"], data), data, method)
    twin_frames = RS.twin_frames(data["T_base_ee"], data["surface"])
    twin = RS.localize(RS.sweeps_of(twin_frames, data), data, method)
    return ref, twin, RS.errors_mm(ref, truths), RS.errors_mm(twin, truths)


@pytest.mark.parametrize("method", RS.METHODS)
def test_the_localizer_on_pymust_frames_accepts_no_wrong_centre(data, method):
    """No centre accepted more than 1 mm off, on pymust's frames or sim_us's; the two
    models agree on which sweeps hold a sphere (on the smooth sphere both reject the bare
    cap: it is not confirmed by its siblings; they parted while the reference's unweighted
    plane waves drew edge-wave echoes under the cap); the refined method's centres on
    pymust's frames within 0.25 mm."""
    ref, twin, e_ref, e_twin = _errors(data, method)
    for r, t, er, et in zip(ref, twin, e_ref, e_twin, strict=True):
        assert not (r.accepted and er > 1.0), r
        assert not (t.accepted and et > 1.0), t
        assert r.accepted == t.accepted, (r.reason, t.reason)
        if r.accepted and method == "refined":
            assert er <= 0.25, er


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="five pymust draws of the diffuse sphere (the number fixed before they were "
    "made): the deepest sweep's median refined error 0.137 mm against sim_us's 0.085 "
    "(1.62x; the middle one 0.074 against 0.049, 1.52x), pymust's deepest centre low in "
    "elevation on average, from the cap's depth read 3 mm to either side of the centre; "
    "the cause is open (README, 'The images against physics'); two draws more leave the "
    "medians where they were, their 90 % bootstrap intervals 0.34-2.64x and 0.76-2.07x",
)
def test_the_refined_error_on_pymust_frames_is_within_1_5_x_sim_us():
    """The issue's criterion on both spheres, with the same imaging on both sides (sim_us
    compounding the reference's three plane waves, apertures Hann-weighted): each refined
    error on pymust's frames within 1.5 × (or 0.02 mm more than) sim_us's error on the
    same scene where both accept the sweep. The diffuse sphere's speckle is a random
    draw on either side (sim_us's error over its realizations spans 3-5×): the median
    over pymust's stored realizations of its scatterers against sim_us's over
    ``SPECKLE_REALIZATIONS`` of its speckle. With the reference counting the elevation
    once and sim_us drawing the elevation delay, three corrected draws gave 1.43 / 0.96 /
    1.05×; all five (the fourth and fifth rendered again), with every echo at a flat
    reflector's level against depth: 0.68 / 1.16 / 1.76×, and with pymust's frames shown
    with the same 0 dB as sim_us's (the elevation focus's, not the cap's depth's):
    0.63 / 1.18 / 1.76×; with the lateral centre read about the cap's top 0.75 / 1.52 /
    1.62× (before the correction, five double-counted draws gave 1.23 / 0.97 / 1.86×)."""
    for surface in RS.SURFACES:
        if not RS.stored_path(surface).exists():
            continue
        data = RS.load_stored(surface)
        if surface == "diffuse":  # realization 0 is among the stored ones
            # The draws fixed before they were made; any later ones are reported, not
            # judged (reference_sweeps.CRITERION_REALIZATIONS).
            reals, errors = RS.reference_errors(surface, criterion_only=True)
            assert reals == list(range(RS.CRITERION_REALIZATIONS))
            e_ref = np.median(errors["refined"], axis=0)
            spread = RS.twin_spread(data)["refined"]
            assert np.isfinite(spread).mean() >= 0.9  # sim_us's sweeps are found
            e_twin = np.nanmedian(spread, axis=0)
        else:
            _, _, e_ref, e_twin = _errors(data, "refined")
        both = np.isfinite(e_ref) & np.isfinite(e_twin)
        assert np.all(e_ref[both] <= np.maximum(1.5 * e_twin[both], e_twin[both] + 0.02)), (
            surface,
            e_ref,
            e_twin,
        )


def test_the_beam_in_water_draws_the_reference_s_psf():
    """A scanner assumes 1540 m/s; in water (≈ 1480 m/s at 20 °C) its delays miss the
    focus. sim_us's lateral kernel in water, for the focused scanner and the compounded
    plane waves, against pymust's displayed PSF of a point there (stored by
    ``reference_sweeps.py --write-psf``): FWHM within 5 %, the main lobe (down to
    -20 dB) within 2.5 dB, the skirts past it within 6 dB. The same scanner imaging at
    its own speed (the beam sim_us drew in water before) is far off: the check can fail."""
    import json

    rec = json.loads(RS.WATER_PSF_STORED.read_text())
    assert rec["offsets_mm"] == list(RS.WATER_PSF_OFFSETS_MM)
    assert rec["depths_mm"] == list(RS.WATER_PSF_DEPTHS_MM)
    for imaging in RS.IMAGING:
        for d, ref in zip(rec["depths_mm"], rec[imaging], strict=True):
            tw = RS.twin_psf(imaging, d * MM)
            assert 0.95 <= tw["fwhm_mm"] / ref["fwhm_mm"] <= 1.05, (imaging, d)
            for r, t in zip(ref["levels_db"], tw["levels_db"], strict=True):
                assert abs(t - r) <= (2.5 if r >= -20.0 else 6.0), (imaging, d, r, t)
    # At the scanner's own speed: the focused beam at 20 mm is ≈ 15 dB narrower 0.3 mm out.
    from sim_us.beam import beam_of

    probe = RS.probe_config("focused")
    ref = rec["focused"][rec["depths_mm"].index(20.0)]
    at_own = beam_of(probe).lateral_profile(20 * MM / RS.axial_scale(probe), [0.0, 0.3 * MM])[0]
    level = 20 * np.log10(at_own[1] / at_own[0])
    assert level < ref["levels_db"][RS.WATER_PSF_OFFSETS_MM.index(0.3)] - 10.0


def test_the_ratio_s_interval_follows_the_draws():
    """The bootstrap interval of pymust's median over sim_us's: about 1 for draws of one
    distribution, excluding 1 for draws twice as large, narrower with more draws, NaN
    with nothing accepted on one side; the same figures for the same draws."""
    # Evenly spread errors (deterministic): the same spread on either side, or doubled.
    twin = np.linspace(0.03, 0.15, 20)
    same = RS.ratio_interval(np.linspace(0.03, 0.15, 7), twin)
    assert same[0] < 1.0 < same[1]
    lo, hi = RS.ratio_interval(2.0 * np.linspace(0.03, 0.15, 40), twin)
    assert 1.0 < lo < 2.0 < hi
    few = RS.ratio_interval(2.0 * np.linspace(0.03, 0.15, 5), twin)
    assert few[1] - few[0] > hi - lo
    assert np.isnan(RS.ratio_interval(np.full(5, np.nan), twin)).all()
    assert RS.ratio_interval(twin[:5], twin) == RS.ratio_interval(twin[:5], twin)


def test_every_stored_realization_is_the_same_scene():
    """The diffuse sphere's further realizations (its scatterers drawn again) image the
    scene and poses realization 0 does, each saying how it was made."""
    if "diffuse" not in [s for s in RS.SURFACES if RS.stored_path(s).exists()]:
        pytest.skip("the diffuse sphere is not stored")
    first = RS.load_stored("diffuse")
    reals = RS.stored_realizations("diffuse")
    assert reals[0] == 0
    for k in reals[1:]:
        data = RS.load_stored("diffuse", k)
        assert data["meta"]["realization"] == k
        assert data["meta"]["command"] == RS.command("diffuse", k)
        # The same method, whether shown again with the focus's 0 dB (``regreyed``: the
        # five rendered before it) or rendered with it.
        method = {k: v for k, v in data["meta"]["method"].items() if k != "regreyed"}
        assert method == {k: v for k, v in first["meta"]["method"].items() if k != "regreyed"}
        for key in ("T_base_ee", "centre_ref", "spacing", "radius", "axial_scale"):
            np.testing.assert_array_equal(data[key], first[key], err_msg=key)
        assert data["frames"].shape == first["frames"].shape
        assert not np.array_equal(data["frames"], first["frames"])  # another draw
