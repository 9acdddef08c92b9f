"""Parameters of the progress engine (:class:`EngineParams`): reading a photo, the evidence cues
(:class:`~nodes.progress.evidence.EvidenceParams`) and the fusion (:class:`~nodes.progress.fusion.FusionParams`).
The streaming node's config and ``constructaide progress --set`` start from these defaults."""

from __future__ import annotations

from dataclasses import dataclass, field

from nodes.progress.evidence import EvidenceParams
from nodes.progress.fusion import FusionParams


@dataclass(frozen=True)
class EngineParams:
    working_width_px: int = 640
    """A photo is read at ``working_scale`` of its width but at least this wide (never wider than it is)."""
    working_scale: float = 0.5
    """Share of a photo's width it is read at (above ``working_width_px``). 0: always ``working_width_px`` (the
    reading until 2026-12-06, 640 px for the default sites' 1920 px frames: their thin and far elements were read
    on too few pixels; BENCHMARKS 'progress notes')."""
    lookahead_days: float = 14.0
    """Candidates: elements planned to start by the photo's date plus this (and every unscheduled one)."""
    work_hours: tuple[float, float] = (7.0, 17.0)
    """Local working hours (Mon-Fri) for the middle of a finish interval."""
    unverified_point_weight: float = 0.3
    """Weight of sparse points triangulated from blind matches (guided ones: 1, looked up on the model: 0)."""
    max_frames_per_camera: int = 400
    material_learn_probability: float = 0.95
    confirm_llr: float = 3.0
    """A transition this strong (and standing since) makes an element's pixels a sample of its material's look."""
    sure_probability: float = 0.9
    """Elements at least this likely to stand before a photo are drawn as built; the rest of the schedule window
    are candidates (their change and looks are read)."""
    dynamic_hides_unseen: bool = False
    """In a fixed camera's photo the dynamic (time-lapse) mask, what changed between the camera's frames, hides only
    the elements seen appearing; candidates and elements only the schedule believes built are read through it where
    they look like their material (:func:`~nodes.progress.occlusion.fixed_camera_hiding`): new beams the occlude
    node took for a mover (they stood one day before the next day's slab covered them). True: it hides every element,
    as the static and user masks do."""
    dynamic_spares_material_like: bool = True
    """... only where the pixel looks like the element's learnt material (False: every pixel of those elements; on the
    synthetic default sites that read passing trucks as elements and called the never-built element built)."""
    peel_passes: int = 1
    """Extra evidence passes without the elements that, with this photo's evidence, most probably do not stand (reads
    what stands behind them)."""
    peel_probability: float = 0.7
    """... those below this P(present) at the photo's time (0.5 until 2026-12-06: BENCHMARKS 'progress notes')."""
    defer_probability: float = 0.0
    """Candidates less likely than this to stand before the photo (mostly elements planned later) are read in a
    pass of their own after the likelier ones, so that a wall planned next week does not hide the beam due today
    (0, default: every candidate in the first pass. 0.25 raised the late class on default seed 0 by 9 points and
    cost built F1 on default seed 7: BENCHMARKS 'progress notes')."""
    unchanged_discount: bool = True
    """A fixed camera's look of an element (appearance, outline) counts only as much as its pixels changed since
    the camera's reference plate (the change cue's ramp from ``change_noise`` to ``change_hit``): unchanged pixels
    repeat what an earlier frame already said (the same background, the same light), they are not new evidence."""
    unchanged_floor: float = 0.25
    """... but at least this share (another day's light is partly a new look; 0: none)."""
    visit_looks_once: bool = False
    """The looks (state evidence) of one phone visit's photos of an element (same local day) count as one look."""
    support_floor: float | None = None
    """An element's appearance is weighed by whether what carries it stands (:func:`~nodes.progress.fusion.coupled`,
    the graph from :func:`~nodes.progress.support.support_graph`) with this floor; None (default): not. Off: on the
    synthetic sites it helped one seed and cost another (BENCHMARKS 'progress notes', support coupling)."""
    dependant_floor: float | None = None
    """... and by whether what it carries does not stand yet, with this floor; None (default): not."""
    support_mean: bool = True
    """... over the mean of the neighbours' probabilities (else their product)."""
    terrain_hides: bool = True
    """Pixels of elements more than ``terrain_margin_m`` below the model's ``terrain_height_m`` (when the site sets
    it) are hidden like masked ones (:func:`~nodes.progress.modelview.below_terrain`): a buried footing shows soil
    standing or not. Off: such elements were read absent in every frame and flagged ``not_built`` (default seeds 0 /
    3 / 7: 10 / 11 / 8 false flags at half width; BENCHMARKS 'progress notes')."""
    terrain_margin_m: float = 0.05
    repeated_no_edge_once: bool = False
    """An element without a change cue (no interior pixels the plate covers: thin, or visible only in a strip beside
    an occlusion mask, where the plate is eroded) seen without an outline by a fixed camera that has a reference
    plate: the missing outline is not counted (the camera's frame without a plate said it once); a found outline
    still is. Off: it keeps standing elements from being read 'not built' by the repeated weak negative outline LLR,
    but the same repeats are what place a late element's appearance, and finish dates moved early (see BENCHMARKS
    progress notes)."""

    evidence: EvidenceParams = field(default_factory=EvidenceParams)
    fusion: FusionParams = field(default_factory=FusionParams)
