"""Threshold-free sphere localization (paper §III-E, "Threshold-Free Sphere Localization").

One module per stage (as PLUS's PatternLocAlgo):

==========================  ==============================================================
module                      stage
==========================  ==============================================================
``settings``                the localizer's settings and per-sweep result
``volume``                  §III-E-1 adaptive brightness, §III-E-2 the sweep volume
``search``                  §III-E-3 count-based exhaustive search (and the specular arc)
``refine``                  §III-E-4 radial-band refinement; the cap's sub-voxel centre
``consensus``               the siblings' consensus and each rejected sweep's reason
``sphere``                  :func:`localize_sphere`: the stages in order; its profile
``baseline``                the fixed-threshold localizer the paper argues against
==========================  ==============================================================

Per sweep:

1. **Adaptive brightness** (``volume``). A pixel is bright when it is above the mean of
   its own frame (no user-chosen intensity cut-off).
2. **Sweep volume** (``volume``). The frames are stacked at the robot-measured spacing;
   once a ``T_ee_us`` is known they are re-stacked into the sweep's reference frame (the
   centre frame's ``us`` frame), which removes the shear a wrong calibration puts into
   the stack.
3. **Count-based exhaustive search** (``search``). Candidate centres on a 1 mm grid over
   the sweep, starting one radius below the face. Each candidate samples a proximal shell
   at radius R (Fibonacci directions) and the proximal half-ball (volume-distributed
   points); each sample takes its nearest voxel and asks whether it is bright. Samples
   outside the acquired volume count in neither numerator nor denominator. The score is
   ``f_shell − f_interior``; its argmax is the seed.
4. **Radial-band refinement** (``refine``). Around the current centres, the bright
   fraction on proximal hemispheres of trial radius, averaged over all sweeps of the
   sphere and normalised to its peak, gives a radial profile: the interior extends to its
   first rising 0.25 crossing, the shell band lies between its 0.75 crossings. Those bands
   replace the initial samples for the refinement passes.

``method="paper"`` stops there (grid-point centres). ``method="refined"`` differs in
seven ways, each for a failure of the paper's score measured on the twin (a bright plate
or floor taken for the sphere in ≈ 10-60 % of sweeps at low gain, a small sphere or a deep
target; a biased centre where the cap saturates):

- *Brightness above the noise floor* (``volume``). A pixel must also stand above its
  depth's noise floor (each image row's median plus two robust σ over the sweep, see
  :func:`frame_levels`): where the gain lifts electronic noise above the frame mean, half
  the water would otherwise be "bright" and a clearly visible cap would fail the
  confinement test; a laterally uniform band (ring-down, a plate) stands out less.
- *The plan's window* (``search``). With ``expected_depth_mm`` (the protocol's target
  depth) the search covers only ± ``expected_window_mm`` about it and about the centre
  line, where the plan put the sphere: where the cap sinks into the noise floor, the
  plate under the sphere (the same spot from every view, so the siblings agree on it) is
  not there to be found.
- *Hypotheses* (``search``). The exhaustive search keeps the grid's ``_HYPOTHESES`` best
  maxima more than R apart and looks at each on a grid twice as fine: a faint thin cap
  straddled by the 1 mm grid recovers its contrast there, a flat reflector does not.
- *Confinement* (``search``, ``sphere``). Each is judged by ``f_shell − max(f_interior,
  f_outer)``, ``f_outer`` the bright share in the band ``_OUTER_BAND`` × R outside the
  sphere on the probe side: water for a sphere, more of the reflector for a plate. A
  detection whose cap does not stand out from that band by ``min_score`` is rejected
  with its reason.
- *The specular arc* (``search``). Where nothing with a sphere's whole cap is found (an
  attenuating gel, a deep target at low gain: the flanks sink below the noise and only
  the cap about normal incidence echoes), a cone of the shell within ``_ARC_DEG`` of the
  beam axis is searched the same way, confined by the band above it and by its tangent
  plane (where a flat reflector lies and a sphere has no echo).
- *The other sweeps as evidence* (``consensus``; with a calibration, ``consensus=True``):
  the centres of one sphere must agree in the robot base. A seed that disagrees with the
  densest cluster is searched again about it; a centre that still disagrees is rejected
  with the distance, and where no three centres agree none is confirmed (see
  ``_consensus``, ``_reject_disagreeing``).
- *Sub-voxel centre* (``refine``) from the moments of the cap's echo (see
  ``_refine_centre``), its elevation from a least-squares parabola through the cap's
  peak grey level per slice, slices clipped at 255 left out (``_elevation_vertex``); a
  centre whose elevation that fit gives only to worse than ``_MAX_ELEVATION_SIGMA``
  (1 σ) is rejected with it, and so is a candidate about which nothing of the cap stands
  above its brightness level (no elevation to read: ``_nothing_to_refine``).

Frames of one sweep share their orientation (a linear sweep); the re-stack applies each
frame's in-plane and elevational offset and treats the frames as parallel (the residual
rotation between frames of a sweep is the robot's repeatability, micro-radians).
"""

from __future__ import annotations

from .baseline import localize_sphere_fixed_threshold
from .refine import profile_bands, profile_crossings, radial_profile
from .search import fibonacci_hemisphere, half_ball_samples, score_candidates, score_grid
from .settings import LocalizerConfig, SweepLocalization, frame_offsets
from .sphere import SphereProfile, apparent_sphere_radius, localize_sphere, sphere_profile
from .volume import SweepVolume, candidate_step, frame_levels, stack_sweep

__all__ = [
    "LocalizerConfig",
    "SphereProfile",
    "SweepLocalization",
    "SweepVolume",
    "apparent_sphere_radius",
    "candidate_step",
    "fibonacci_hemisphere",
    "frame_levels",
    "frame_offsets",
    "half_ball_samples",
    "localize_sphere",
    "localize_sphere_fixed_threshold",
    "profile_bands",
    "profile_crossings",
    "radial_profile",
    "score_candidates",
    "score_grid",
    "sphere_profile",
    "stack_sweep",
]
