"""The documents the ground station emits and stores: one serializer for the CLI, the API and the archive.

Inside the program everything is a typed object (:class:`app.extraction.Extraction`,
:class:`app.identification.Candidate`, :class:`app.attitude.sequence.SequenceFit`,
...).  This module is the only place that turns them into JSON and back:

* ``XDocument.of(...)`` builds a document from the typed objects;
* ``model_dump(mode="json")`` is the JSON that the CLI prints, the API answers
  (the endpoints declare these models as their ``response_model``, so
  ``/docs`` shows every field) and the archive stores;
* ``XDocument.model_validate(json)`` parses a stored document once into a
  typed object again, and the few numeric members that code needs as arrays
  have a property for that (``CandidateDocument.rotation``).

Stored documents written by older versions parse too: members added later have
defaults, and unknown members are ignored.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from app.extraction import EXTRACTION_VERSION, Extraction, Pattern, Track, carried_tracks, seed_pattern, \
    tracks_pattern
from app.timefmt import utc_text


class Document(BaseModel):
    """Base of every document: members in declaration order, unknown stored members ignored."""

    model_config = ConfigDict(extra="ignore")


def _rounded(value: float | None, digits: int | None = 3) -> float | None:
    """A finite float rounded to ``digits`` (None: kept exact); None for NaN, infinities and None."""
    if value is None or not math.isfinite(value):
        return None
    return float(value) if digits is None else round(float(value), digits)


# ---------------------------------------------------------------------------
# Patterns and extraction
# ---------------------------------------------------------------------------

class PatternPoint(Document):
    """One point of a pattern, in the reference snapshot's pixels."""

    track: int | None = Field(description="track id; null for a point picked by hand")
    x: float | None
    y: float | None
    brightness: float | None
    sightings: int = Field(description="snapshots averaged into the point")
    sigma_px: float | None = Field(description="estimated 1-sigma position error, pixels")

    @classmethod
    def rows(cls, pattern: Pattern) -> list["PatternPoint"]:
        return [cls(track=int(t) if t >= 0 else None, x=_rounded(xy[0]), y=_rounded(xy[1]),
                    brightness=_rounded(b), sightings=int(n), sigma_px=_rounded(s))
                for t, xy, b, n, s in zip(pattern.track_ids, pattern.xy, pattern.brightness,
                                          pattern.sightings, pattern.sigma_px)]


class TrackDocument(Document):
    id: int
    snapshots: list[int] = Field(description="0-based positions of the snapshots where the track was seen")
    xy: list[list[float]]
    mean_brightness: float | None


class ExtractionDocument(Document):
    """Tracked stars vs ghosts, hot pixels and outliers (``python -m app extract --json``, stored with each upload).

    ``sources`` holds, per snapshot, the track id (or null) of every input
    source in input order, ``rejected`` the reason (``ghost``, ``hot_pixel``,
    ``outlier``) or null.  ``motion[i]`` carries snapshot i's camera vectors
    into the reference snapshot's frame (null where unknown).  The stored
    document is authoritative: patterns refer to its track ids, so the
    archive never re-runs extraction (see :meth:`to_extraction`).
    ``hot_pixel_map`` is the version of the spacecraft camera's hot-pixel map
    whose pixels were given to extraction as known hot pixels (spot-list
    uploads to the archive; null: none, as for the command line and for
    uploads stored before maps were applied).
    """

    version: int | None = Field(default=None, description="extraction version that made it (null: before version 1)")
    reference_snapshot: int
    sources: list[list[int | None]]
    rejected: list[list[str | None]]
    tracks: list[TrackDocument]
    pattern: list[PatternPoint]
    seed_pattern: list[PatternPoint]
    noise_px: float | None = Field(description="estimated 1-sigma position noise of one sighting, pixels")
    notes: list[str]
    motion: list[list[list[float]] | None] | None = None
    hot_pixel_map: int | None = Field(default=None, description="version of the camera's hot-pixel map applied "
                                                               "to the sources (null: none)")

    @classmethod
    def of(cls, extraction: Extraction, hot_pixel_map: int | None = None) -> "ExtractionDocument":
        return cls(
            version=EXTRACTION_VERSION,
            reference_snapshot=int(extraction.reference),
            sources=[[int(t) if t >= 0 else None for t in per] for per in extraction.track_of_source],
            rejected=[list(per) for per in extraction.rejection],
            tracks=[TrackDocument(id=int(t.id), snapshots=[int(s) for s in t.snapshots],
                                  xy=[[round(float(x), 3), round(float(y), 3)] for x, y in t.xy],
                                  mean_brightness=_rounded(t.mean_brightness, None))
                    for t in extraction.tracks],
            pattern=PatternPoint.rows(extraction.pattern),
            seed_pattern=PatternPoint.rows(extraction.seed_pattern),
            noise_px=_rounded(extraction.noise_px, None),
            notes=list(extraction.notes),
            motion=[m.tolist() if np.all(np.isfinite(m)) else None for m in extraction.motion],
            hot_pixel_map=hot_pixel_map)

    @property
    def complete(self) -> bool:
        """Whether the document holds everything :meth:`to_extraction` needs (version 1 and later)."""
        return self.version is not None and self.motion is not None and self.noise_px is not None

    def to_extraction(self, sequence) -> Extraction:
        """The :class:`Extraction` this document describes, for ``sequence`` (the telemetry it came from).

        Sighting positions come from the telemetry itself (exact), the
        motion and the noise from the document (stored unrounded), and the
        patterns are rebuilt from them by the functions extraction itself
        uses, so the result equals the extraction that was stored.
        """
        if not self.complete:
            raise ValueError("the stored extraction predates extraction version 1 (no motion)")
        track_of_source = tuple(np.array([-1 if t is None else t for t in per], dtype=int) for per in self.sources)
        tracks = []
        for t in self.tracks:
            snapshots = np.array(t.snapshots, dtype=int)
            indices = np.array([int(np.flatnonzero(track_of_source[s] == t.id)[0]) for s in snapshots], dtype=int)
            xy = np.array([sequence.snapshots[s].xy[i] for s, i in zip(snapshots, indices)], dtype=float).reshape(-1, 2)
            tracks.append(Track(id=t.id, snapshots=snapshots, source_indices=indices, xy=xy,
                                mean_brightness=float(t.mean_brightness)))
        motion = np.array([np.full((3, 3), np.nan) if m is None else m for m in self.motion], dtype=float)
        camera = sequence.camera
        return Extraction(reference=self.reference_snapshot, track_of_source=track_of_source,
                          rejection=tuple(tuple(per) for per in self.rejected), tracks=tuple(tracks),
                          motion=motion, pattern=tracks_pattern(camera, motion, carried_tracks(tracks, motion),
                                                                self.noise_px),
                          seed_pattern=seed_pattern(camera, self.reference_snapshot, tracks, self.noise_px),
                          noise_px=self.noise_px, notes=tuple(self.notes))


class ManualPointDefinition(Document):
    snapshot: int
    x: float
    y: float


class PatternDefinition(Document):
    """The operator's pattern: tracks out, tracks in (null: every track), points picked by hand."""

    exclude_tracks: list[int] = Field(default_factory=list)
    include_tracks: list[int] | None = None
    manual_points: list[ManualPointDefinition] = Field(default_factory=list)


class PatternDocument(Document):
    """The current pattern of a sequence: its stored definition and the points it gives."""

    version: int | None
    kind: Literal["automatic", "edit", "reset"]
    operator: str | None
    created_at: str | None
    definition: PatternDefinition
    points: list[PatternPoint]
    reference_snapshot: int


# ---------------------------------------------------------------------------
# Candidates and searches
# ---------------------------------------------------------------------------

class StarMatchDocument(Document):
    pattern_index: int = Field(description="row of the searched pattern")
    track: int | None
    hip: int
    name: str | None
    residual_arcsec: float


class PlanetMatchDocument(Document):
    pattern_index: int
    track: int | None
    name: str
    residual_arcsec: float


class SequenceFitDocument(Document):
    """The constant-rate fit of the whole sequence (:mod:`app.attitude.sequence`)."""

    rate_deg_s: list[float] = Field(description="body rate in camera axes, deg/s")
    rate_sigma_deg_s: list[float]
    snapshots_used: int
    chi2_reduced: float

    @classmethod
    def of(cls, fit) -> "SequenceFitDocument":
        return cls(rate_deg_s=[round(math.degrees(w), 7) for w in fit.rate_rad_s],
                   rate_sigma_deg_s=[round(math.degrees(math.sqrt(v)), 7) for v in np.diag(fit.rate_covariance)],
                   snapshots_used=len(fit.snapshots), chi2_reduced=round(fit.chi2_reduced, 3))

    @property
    def rate_rad_s(self) -> np.ndarray:
        return np.radians(np.array(self.rate_deg_s, dtype=float))


class CameraFitDocument(Document):
    """The optics fitted with a candidate's attitude (:mod:`app.identification.optics`).

    Only the fitted parameters have values (the focal length from 3 matched
    stars, k1 from 6); ``sigma`` holds their 1-sigma.  ``adopted``: the
    candidate's matches and attitude use this camera (the data asked for it,
    or the pattern was found at a searched focal length); otherwise the
    declared camera stands and this is for information.
    """

    focal_length_px: float | None = None
    k1: float | None = None
    k2: float | None = None
    cx: float | None = None
    cy: float | None = None
    sigma: dict[str, float]
    rms_px: float
    adopted: bool

    over: Literal["pattern", "sequence"] = Field(
        description="fitted on the searched pattern, or over every snapshot's sightings of the sequence")

    @classmethod
    def of(cls, fit, adopted: bool) -> "CameraFitDocument":
        """Of an :class:`app.camera_fit.CameraAttitudeFit` (the pattern) or a ``Calibration`` (the sequence)."""
        optics = fit.camera.optics()
        over_sequence = hasattr(fit, "rms_px_after")
        return cls(**{name: round(float(optics[name]), 8) for name in fit.parameters},
                   sigma={name: float(f"{value:.4g}") for name, value in fit.sigma.items()},
                   rms_px=round(float(fit.rms_px_after if over_sequence else fit.rms_px), 4), adopted=adopted,
                   over="sequence" if over_sequence else "pattern")


class CandidateDocument(Document):
    """One ranked attitude candidate (docs/cli-and-api.md, "Formats")."""

    rank: int
    deviation_arcsec: float
    deviation_px_per_point: float
    rms_arcsec: float | None
    false_match_probability: float
    ra_deg: float
    dec_deg: float
    roll_deg: float
    quaternion: list[float] = Field(description="scalar-last [x, y, z, w] of rotation_matrix")
    rotation_matrix: list[list[float]] = Field(description="ICRS -> camera at the reference snapshot")
    matches: list[StarMatchDocument]
    planets: list[PlanetMatchDocument]
    generating_edge: list[int]
    generating_pair_hip: list[int]
    n_matched: int
    n_hypotheses_merged: int = 1
    sigma_cross_boresight_arcsec: float | None = None
    sigma_roll_arcsec: float | None = None
    sequence_fit: SequenceFitDocument | None = None
    camera_fit: CameraFitDocument | None = None
    focal_length_px: float | None = Field(None, description="the focal length this candidate was identified "
                                          "with, when not the declared one (fitted, or found by a search of the "
                                          "field of view)")
    fov_deg: float | None = Field(None, description="the horizontal field of view at that focal length")
    centre_ra_deg: float | None = Field(None, description="RA of the image's centre pixel (ra_deg is the "
                                        "boresight's, the principal point's: the same for a centred lens)")
    centre_dec_deg: float | None = Field(None, description="Dec of the image's centre pixel")

    def matched_camera(self, declared):
        """The camera this candidate's stars were matched with (an :class:`app.camera.Camera`): the optics
        fitted with it where it adopted them, else the focal length it was found at (a searched focal
        length, or the field of view found when the optics were unknown), else ``declared``."""
        fit = self.camera_fit
        if fit is not None and fit.adopted:
            return declared.with_optics(focal_length_px=fit.focal_length_px, cx=fit.cx, cy=fit.cy, k1=fit.k1,
                                        k2=fit.k2)
        if self.focal_length_px is not None:
            return declared.with_optics(focal_length_px=self.focal_length_px)
        return declared

    @classmethod
    def of(cls, candidate, fit=None) -> "CandidateDocument":
        """The document of an :class:`app.identification.Candidate` and its sequence fit (if any)."""
        ra, dec, roll = candidate.radec_roll_deg
        return cls(
            rank=candidate.rank,
            deviation_arcsec=round(candidate.deviation_arcsec, 3),
            deviation_px_per_point=round(candidate.deviation_px_per_point, 4),
            rms_arcsec=_rounded(candidate.rms_arcsec),
            false_match_probability=float(f"{candidate.false_match_probability:.3g}"),
            ra_deg=round(ra, 7), dec_deg=round(dec, 7), roll_deg=round(roll, 6),
            quaternion=[round(float(x), 10) for x in candidate.quaternion],
            rotation_matrix=[[round(float(x), 10) for x in row] for row in candidate.rotation_matrix],
            matches=[StarMatchDocument(pattern_index=m.pattern_index, track=m.track, hip=m.hip, name=m.name,
                                       residual_arcsec=round(m.residual_arcsec, 3)) for m in candidate.matches],
            planets=[PlanetMatchDocument(pattern_index=p.pattern_index, track=p.track, name=p.name,
                                         residual_arcsec=round(p.residual_arcsec, 3)) for p in candidate.planets],
            generating_edge=list(candidate.generating_edge),
            generating_pair_hip=list(candidate.generating_pair_hip),
            n_matched=candidate.n_matched, n_hypotheses_merged=int(candidate.n_hypotheses_merged),
            sigma_cross_boresight_arcsec=_rounded(candidate.sigma_cross_boresight_arcsec),
            sigma_roll_arcsec=_rounded(candidate.sigma_roll_arcsec),
            sequence_fit=None if fit is None else SequenceFitDocument.of(fit),
            focal_length_px=None if candidate.camera is None else round(candidate.camera.focal_length_px, 3),
            fov_deg=None if candidate.camera is None else round(candidate.camera.fov_deg[0], 5),
            centre_ra_deg=None if candidate.centre_radec_deg is None else round(candidate.centre_radec_deg[0], 7),
            centre_dec_deg=None if candidate.centre_radec_deg is None else round(candidate.centre_radec_deg[1], 7),
            camera_fit=None if candidate.camera_fit is None else CameraFitDocument.of(
                candidate.camera_fit, adopted=candidate.camera is not None
                and candidate.camera.optics() == candidate.camera_fit.camera.optics()))

    @property
    def rotation(self) -> np.ndarray:
        """``rotation_matrix`` as a (3, 3) array."""
        return np.array(self.rotation_matrix, dtype=float)

    @property
    def unit_quaternion(self) -> list[float]:
        """``quaternion`` renormalised (it is stored rounded to 10 digits)."""
        q = np.array(self.quaternion, dtype=float)
        return list(q / np.linalg.norm(q))


class FocalLengthContradictionDocument(Document):
    """The stars contradict the declared focal length (:class:`app.identification.FocalLengthContradiction`):
    the pattern's bright triangles fit one outside the declared tolerance, where nothing is searched."""

    focal_length_px: float = Field(description="the focal length the stars fit")
    declared_focal_length_px: float
    offset: float = Field(description="focal_length_px / declared_focal_length_px - 1")
    declared_tolerance: float = Field(description="the declared focal_length_tolerance, a fraction")
    n_matched: int = Field(description="pattern points on stars at that focal length")
    n_points: int
    ra_deg: float = Field(description="where the camera points at that focal length")
    dec_deg: float
    roll_deg: float
    note: str = Field(description="what it means for the operator, in a sentence")

    @classmethod
    def of(cls, contradiction) -> "FocalLengthContradictionDocument | None":
        if contradiction is None:
            return None
        ra, dec, roll = contradiction.radec_roll_deg
        return cls(focal_length_px=round(contradiction.focal_length_px, 3),
                   declared_focal_length_px=round(contradiction.declared_focal_length_px, 3),
                   offset=round(contradiction.offset, 6), declared_tolerance=contradiction.declared_tolerance,
                   n_matched=contradiction.n_matched, n_points=contradiction.n_points,
                   ra_deg=round(ra, 4), dec_deg=round(dec, 4), roll_deg=round(roll, 4), note=contradiction.note())


class SearchResult(Document):
    """What one identification run found: the archive stores exactly this."""

    status: Literal["identified", "ambiguous", "no_match"]
    method: str
    reference_snapshot: int
    reference_time: str
    pattern_version: int | None
    pattern: list[PatternPoint] = Field(description="the searched pattern; candidates' pattern_index are its rows")
    candidates: list[CandidateDocument]
    notes: list[str]
    elapsed_ms: float
    focal_length_contradiction: FocalLengthContradictionDocument | None = None

    def candidate(self, rank: int) -> CandidateDocument | None:
        return next((c for c in self.candidates if c.rank == rank), None)


class SearchDocument(SearchResult):
    """A stored search as the API returns it."""

    search_id: int
    sequence: int
    created_at: str
    reused: bool = Field(default=False, description="true: answered from the archive (same pattern and options)")

    @classmethod
    def of(cls, search, reused: bool = False) -> "SearchDocument":
        """The document of an archived search (:class:`app.storage.SearchRow`)."""
        return cls(**search.result, search_id=search.id, sequence=search.seq_id,
                   created_at=utc_text(search.created_at), reused=reused)


class SolveDocument(Document):
    """One line of ``python -m app solve --json``."""

    file: str
    sequence_id: str | None
    status: Literal["identified", "ambiguous", "no_match", "invalid"]
    error: str | None = None
    input_sha256: str | None = Field(
        default=None, description="what the answer was made from (app.workflow.files.input_sha256): a re-run of "
                                  "batch --out solves a file again when this changed; null if it could not be read")
    reference_snapshot: int | None = None
    sources: list[list[int | None]] = Field(default_factory=list)
    source_stars: list[list[int | None]] | None = Field(
        None, description="per snapshot and source in input order, the HIP number of the star the first "
                          "candidate names it (null: no star there, or none certainly; a note counts those); "
                          "null when that candidate is not credible")
    candidates: list[CandidateDocument] = Field(default_factory=list)
    elapsed_ms: float | None = None
    notes: list[str] = Field(default_factory=list)
    focal_length_contradiction: FocalLengthContradictionDocument | None = None
    tf_status: str | None = None
    tf_candidates: list[CandidateDocument] | None = None
    methods_agree: bool | None = None


class ExtractDocument(Document):
    """One line of ``python -m app extract --json``: the extraction members, null for an invalid file."""

    file: str
    sequence_id: str | None
    status: Literal["ok", "invalid"]
    error: str | None = None
    reference_snapshot: int | None = None
    sources: list[list[int | None]] | None = None
    rejected: list[list[str | None]] | None = None
    tracks: list[TrackDocument] | None = None
    pattern: list[PatternPoint] | None = None
    seed_pattern: list[PatternPoint] | None = None
    noise_px: float | None = None
    notes: list[str] | None = None


# ---------------------------------------------------------------------------
# Sequences, confirmations, the view
# ---------------------------------------------------------------------------

class SequenceSummary(Document):
    id: int
    sequence_id: str | None
    spacecraft: str | None
    filename: str | None
    camera: dict[str, Any] | None
    first_time: str | None = Field(description="time of the first snapshot (UTC); null when the times are only "
                                               "assumed (frames that carried none: its telemetry's time_assumed)")
    n_snapshots: int | None
    uploaded_at: str | None
    status: Literal["new", "identified", "ambiguous", "no_match", "confirmed", "rejected"]
    content_sha256: str

    @classmethod
    def of(cls, row) -> "SequenceSummary":
        return cls(id=row.id, sequence_id=row.sequence_id, spacecraft=row.spacecraft, filename=row.filename,
                   camera=row.camera, first_time=utc_text(row.first_time), n_snapshots=row.n_snapshots,
                   uploaded_at=utc_text(row.uploaded_at), status=row.status, content_sha256=row.content_sha256)


class SequencePage(Document):
    items: list[SequenceSummary]
    total: int
    offset: int
    limit: int


class UploadDocument(Document):
    """The answer to an upload: the stored sequence, its extraction and current pattern.

    Uploads are told apart by their exact bytes (``content_sha256``), so the same telemetry sent again
    with CRLF line endings or a UTF-8 byte-order mark is stored as a second sequence.
    ``same_sequence_id_as`` and ``note`` say so: the other stored uploads with this spacecraft and
    sequence id, and a sentence for the operator (see :func:`app.workflow.archive.same_sequence_note`).
    """

    id: int
    created: bool = Field(description="false: the same content was stored before")
    sequence: SequenceSummary
    extraction: ExtractionDocument
    pattern: PatternDocument
    same_sequence_id_as: list[int] = Field(
        default_factory=list,
        description="archive ids of the other stored uploads with the same spacecraft and sequence id, oldest "
                    "first (their telemetry differs in bytes: line endings, byte-order mark or content); empty "
                    "when there are none")
    note: str | None = Field(
        default=None, description="for the operator, when same_sequence_id_as is not empty: which other uploads "
                                  "have the same spacecraft and sequence id; null otherwise")


class PatternUsed(Document):
    """The pattern a confirmation was made on (its version may no longer be the current one)."""

    version: int | None
    points: list[PatternPoint]
    definition: PatternDefinition


class AttitudeDocument(Document):
    """A confirmed attitude with its audit record."""

    id: int
    sequence: int
    sequence_id: str | None
    spacecraft: str | None
    search_id: int | None
    rank: int
    operator: str
    confirmed_at: str
    comment: str | None
    epoch: str | None = Field(description="time of the reference snapshot (UTC)")
    ra_deg: float
    dec_deg: float
    roll_deg: float
    quaternion: list[float]
    rotation_matrix: list[list[float]]
    rate_deg_s: list[float] | None = Field(description="fitted body rate (camera axes), when the sequence had one")
    deviation_arcsec: float | None
    false_match_probability: float | None
    pattern: PatternUsed
    candidate: CandidateDocument
    superseded_by: int | None
    current: bool
    apm_url: str
    aem_url: str | None
    acm_url: str = Field(description="CCSDS ACM 2.0: states per snapshot, rate, determination and covariance")
    override_reason: str | None = Field(default=None, description="why the operator confirmed past the guard "
                                        "rail (a candidate not the credible best, a stale or doubtful search)")
    overridden: list[str] = Field(default_factory=list, description="the guard rail's reasons that were overridden")
    withdrawn_by: int | None = Field(default=None, description="the rejection (no valid attitude) that withdrew it")
    replaces_rejection: int | None = Field(default=None, description="the rejection it replaced as the verdict")


    @classmethod
    def of(cls, c, row) -> "AttitudeDocument":
        """The document of a confirmation (:class:`app.storage.ConfirmationRow`) of sequence ``row``."""
        return cls(id=c.id, sequence=c.seq_id, sequence_id=row.sequence_id if row else None,
                   spacecraft=row.spacecraft if row else None, search_id=c.search_id, rank=c.rank,
                   operator=c.operator, confirmed_at=utc_text(c.confirmed_at), comment=c.comment,
                   epoch=utc_text(c.epoch), ra_deg=c.ra_deg, dec_deg=c.dec_deg, roll_deg=c.roll_deg,
                   quaternion=c.quaternion, rotation_matrix=c.rotation_matrix, rate_deg_s=c.rate_deg_s,
                   deviation_arcsec=c.deviation_arcsec, false_match_probability=c.false_match_probability,
                   pattern=PatternUsed.model_validate(c.pattern), candidate=CandidateDocument.model_validate(c.candidate),
                   superseded_by=c.superseded_by, current=c.is_current, apm_url=f"/api/attitudes/{c.id}/apm",
                   aem_url=f"/api/attitudes/{c.id}/aem" if c.aem_text else None,
                   acm_url=f"/api/attitudes/{c.id}/acm",
                   override_reason=getattr(c, "override_reason", None), overridden=getattr(c, "overridden", None) or [],
                   withdrawn_by=getattr(c, "withdrawn_by", None),
                   replaces_rejection=getattr(c, "replaces_rejection", None))


class AttitudePage(Document):
    items: list[AttitudeDocument]
    total: int
    offset: int
    limit: int


class SequenceDetail(SequenceSummary):
    telemetry: dict[str, Any] = Field(description="the upload in the tubsat-snapshots/1 JSON form")
    extraction: ExtractionDocument
    pattern: PatternDocument
    search: SearchDocument | None
    confirmation: AttitudeDocument | None


class CandidateView(Document):
    """One candidate of the latest search with its sky section (:mod:`app.workflow.skyview`)."""

    sequence: int
    search_id: int
    status: str
    rank: int
    n_candidates: int
    reference_snapshot: int
    reference_time: str
    candidate: CandidateDocument
    sky: dict[str, Any]


class ConfirmRequestDocument(Document):
    """A confirmation the 3D view sent to this session's console (:class:`app.workflow.view_state.ConfirmRequest`):
    the console opens its second step for that rank of that search."""

    sequence: int
    rank: int
    search_id: int | None
    number: int = Field(description="grows with every request: a console takes each one once")
    comment: str | None = Field(default=None, description="the comment typed with it in the 3D view")


class ViewDocument(Document):
    """The shared view state and what the archive says about its sequence now."""

    sequence: int | None
    rank: int | None
    mag: float
    revision: int
    updated_by: str
    updated_at: str | None
    search_id: int | None = None
    n_candidates: int = 0
    status: str | None = None
    pattern_version: int | None = None
    confirmation_id: int | None = None
    session: str | None = Field(default=None, description="the console session this state belongs to")
    followed_by_3d: bool = Field(default=False, description="the 3D view at its bare address draws this session "
                                   "(each console also has its own: GET /api/viewer?session=...)")
    rejection_id: int | None = Field(default=None, description="the current verdict, when it is 'no valid attitude'")
    operator: str | None = Field(default=None, description="the operator named in this session's console (the 3D "
                                                            "view's Confirm uses it)")
    confirm_request: ConfirmRequestDocument | None = Field(
        default=None, description="the 3D view's latest confirmation that needs this console's second step")


class ViewerDocument(Document):
    available: bool
    url: str | None = Field(description="the 3D view's page; with a session, a view drawing that console session")
    host: str | None = None
    port: int | None = None
    detail: str | None = None
    session: str | None = Field(default=None, description="the console session the url's view draws")
    views: int | None = Field(default=None, description="3D views drawn now (browser clients admitted)")
    max_views: int | None = Field(default=None, description="3D views drawn at most at once; one more is refused")


class IndexHealth(Document):
    loaded: bool
    stars: int | None = None
    pairs: int | None = None
    mag_limit: float | None = None


class HealthDocument(Document):
    status: Literal["ok", "degraded"]
    db: dict[str, Any]
    index: IndexHealth
    auth_required_for_writes: bool
    max_upload_bytes: int
    search_timeout_s: float
    search_workers: str
    compute_ready: bool = Field(description="false while the searches' workers load their compiled kernels "
                                            "(a second; the first start after an install compiles them, 30-60 s): "
                                            "searches and uploads sent meanwhile wait for them, and their time-out "
                                            "counts from then")


# ---------------------------------------------------------------------------
# Camera calibrations
# ---------------------------------------------------------------------------

class CovarianceDocument(Document):
    names: list[str]
    matrix: list[list[float]]


class ResidualCell(Document):
    x: float = Field(description="centre of the cell, pixels")
    y: float
    n: int = Field(description="inlier stars in the cell")
    dx_before: float = Field(description="mean measured-minus-predicted x with the declared camera, px")
    dy_before: float
    dx_after: float = Field(description="the same with the fitted camera")
    dy_after: float


class ResidualMap(Document):
    """Mean residual vectors over a grid on the sensor, before and after a calibration."""

    columns: int
    rows: int
    width: int
    height: int
    cells: list[ResidualCell]


class CalibrationDocument(Document):
    """A camera fitted over many sequences (``python -m app calibrate --json``, and what the archive stores)."""

    camera: dict[str, Any] = Field(description="the fitted camera, with the keys of the telemetry camera object")
    sigma: dict[str, float] = Field(description="1-sigma of each fitted parameter")
    covariance: CovarianceDocument = Field(description="of the fitted parameters, attitudes marginalised")
    sequences_used: int
    observations_used: int = Field(description="snapshots")
    stars_used: int
    stars_rejected: int
    rms_px_before: float = Field(description="rms residual with the declared camera (attitudes refitted)")
    rms_px_after: float
    chi2_reduced: float
    residual_map: ResidualMap | None = None
    notes: list[str] = Field(default_factory=list, description="what was left out, and why")

    @classmethod
    def of(cls, calibration, residual_map: ResidualMap | None = None,
           notes: list[str] | None = None) -> "CalibrationDocument":
        """The document of an :class:`app.camera_fit.Calibration` (and its residual map)."""
        return cls(camera=calibration.camera.to_dict(),
                   sigma={name: float(f"{value:.4g}") for name, value in calibration.sigma.items()},
                   covariance=CovarianceDocument(names=list(calibration.parameters),
                                                 matrix=calibration.covariance.tolist()),
                   sequences_used=calibration.sequences_used, observations_used=calibration.observations_used,
                   stars_used=calibration.stars_used, stars_rejected=calibration.stars_rejected,
                   rms_px_before=round(calibration.rms_px_before, 4), rms_px_after=round(calibration.rms_px_after, 4),
                   chi2_reduced=round(calibration.chi2_reduced, 4), residual_map=residual_map,
                   notes=list(notes or []))


class StoredCalibration(CalibrationDocument):
    """A calibration as the archive keeps it: the spacecraft's version N, who made it, when, from what."""

    spacecraft: str
    version: int
    operator: str | None
    created_at: str
    sequences: list[int] = Field(description="archive ids of the sequences whose stars it was fitted on")

    @classmethod
    def of(cls, row) -> "StoredCalibration":
        """The document of an :class:`app.storage.CalibrationRow`."""
        return cls(**row.result, spacecraft=row.spacecraft, version=row.version, operator=row.operator,
                   created_at=utc_text(row.created_at), sequences=row.sequences)


# ---------------------------------------------------------------------------
# Operator review: candidate verdicts, rejections, the work queue
# ---------------------------------------------------------------------------

class CandidateVerdict(Document):
    """Whether one candidate of the latest search may be confirmed without a second step, and why not."""

    rank: int
    credible: bool = Field(description="the credible best: rank 1 of an 'identified' search on the current pattern")
    reasons: list[str] = Field(description="why it is not credible (empty when it is); confirming it anyway needs "
                                           "override_reason")
    deviation_gap_arcsec: float | None = Field(description="its deviation minus rank 1's")
    odds_vs_best: float | None = Field(description="log10 of its false-match probability over rank 1's: how many "
                                                   "decades likelier it is to be chance")
    separation_from_best_deg: float | None = Field(description="rotation angle between its attitude and rank 1's")


class RejectionDocument(Document):
    """An operator's verdict "no valid attitude" with its reason (append-only audit record)."""

    id: int
    sequence: int
    sequence_id: str | None
    spacecraft: str | None
    search_id: int | None
    operator: str
    rejected_at: str
    reason: str
    replaces_confirmation: int | None
    replaces_rejection: int | None
    current: bool

    @classmethod
    def of(cls, r, row) -> "RejectionDocument":
        """The document of a rejection (:class:`app.storage.RejectionRow`) of sequence ``row``."""
        return cls(id=r.id, sequence=r.seq_id, sequence_id=row.sequence_id if row else None,
                   spacecraft=row.spacecraft if row else None, search_id=r.search_id, operator=r.operator,
                   rejected_at=utc_text(r.rejected_at), reason=r.reason,
                   replaces_confirmation=r.replaces_confirmation, replaces_rejection=r.replaces_rejection,
                   current=r.is_current)


class AuditEntry(Document):
    """One verdict in a sequence's audit trail, oldest first."""

    kind: Literal["confirmed", "rejected"]
    id: int = Field(description="attitude id (confirmed) or rejection id (rejected)")
    operator: str
    at: str
    rank: int | None = None
    search_id: int | None = None
    reason: str | None = Field(default=None, description="the rejection's reason, or the override reason")
    comment: str | None = None
    current: bool


class ReviewDocument(Document):
    """What an operator needs to judge a sequence: each candidate's verdict and the sequence's own."""

    sequence: int
    status: str
    search_id: int | None
    search_status: str | None
    method: str | None
    search_pattern_version: int | None
    pattern_version: int | None
    stale: bool = Field(description="the pattern changed since the latest search")
    identified_probability: float = Field(description="a best candidate is 'identified' at most this likely by chance")
    candidates: list[CandidateVerdict]
    confirmation: AttitudeDocument | None = Field(description="the current verdict when it is a confirmation")
    rejection: RejectionDocument | None = Field(description="the current verdict when it is 'no valid attitude'")
    audit: list[AuditEntry]


class SpacecraftDocument(Document):
    name: str | None
    sequences: int


class OperatorDocument(Document):
    """Who the console writes as: the bearer token's operator, or the name typed (loopback)."""

    auth_required: bool
    operator: str | None = Field(description="the token's operator (null: no token sent)")


# ---------------------------------------------------------------------------
# Frame previews
# ---------------------------------------------------------------------------

class FrameDetection(Document):
    """A detection reported as a source of the snapshot (full-resolution pixels)."""

    source: int = Field(description="index of the source in the snapshot (file order): what the extraction's "
                                    "`sources[snapshot][source]` names the track of")
    x: float
    y: float
    brightness: float | None = None
    flags: list[str] = Field(default_factory=list, description="the detector's flags: saturated, edge")


class FrameRejected(Document):
    """A blob of the frame that is not a source, and why."""

    x: float
    y: float
    reason: str = Field(description="hot_pixel, mapped_hot_pixel, elongated (a trail), extended, border (cut by "
                                    "the frame's edge and no whole point source), row (side by side with others: "
                                    "text, a treeline), no_flux (no light above the sky in its aperture), "
                                    "not_brightest (a star beyond the brightest reported), joined by '+' with other "
                                    "flags")


class FrameOverlay(Document):
    """What is drawn over a frame: full-resolution pixels, (0, 0) the centre of the top-left pixel."""

    detections: list[FrameDetection] = Field(default_factory=list)
    rejected: list[FrameRejected] = Field(default_factory=list, description="the brightest 200 at most")
    rejected_total: int = 0
    hot_pixels: list[tuple[int, int]] = Field(default_factory=list,
                                              description="(x, y) of the camera's hot-pixel map applied to the pass")
    hot_pixels_total: int = 0


class FramePreviewInfo(Document):
    """One snapshot's frame preview (the image is at ``url``)."""

    snapshot: int = Field(description="snapshot index (time order, from 0)")
    width: int = Field(description="the frame's width, pixels")
    height: int = Field(description="the frame's height, pixels")
    scale: int = Field(description="each image pixel is the mean of scale x scale frame pixels; image pixel (i, j) "
                                   "is centred on frame pixel ((j + 0.5) scale - 0.5, (i + 0.5) scale - 0.5)")
    image_width: int = Field(description="the PNG's width: ceil(width / scale)")
    image_height: int = Field(description="the PNG's height: ceil(height / scale)")
    url: str
    overlay: FrameOverlay

    @classmethod
    def of(cls, seq_id: int, row) -> "FramePreviewInfo":
        """From a stored :class:`app.storage.FramePreviewRow`."""
        return cls(snapshot=row.snapshot, width=row.width, height=row.height, scale=row.scale,
                   image_width=row.image_width, image_height=row.image_height,
                   url=f"/api/sequences/{seq_id}/frames/{row.snapshot}.png",
                   overlay=FrameOverlay.model_validate(row.overlay))


class FramePreviewsDocument(Document):
    """The frame previews of a sequence (``GET /api/sequences/{id}/frames``): empty for spot-list uploads
    and for frames uploaded before previews were kept."""

    sequence: int
    max_png_bytes: int = Field(description="largest PNG kept of one frame; a larger one is made at twice the scale")
    frames: list[FramePreviewInfo]


# ---------------------------------------------------------------------------
# A spacecraft's attitude timeline (app.workflow.timeline)
# ---------------------------------------------------------------------------

class TimelinePoint(Document):
    """One sequence on a spacecraft's timeline: its span, status, who gave it, and its attitude if it has one."""

    sequence: int = Field(description="archive id")
    sequence_id: str | None
    filename: str | None
    status: Literal["new", "identified", "ambiguous", "no_match", "confirmed", "rejected"]
    by: str | None = Field(description="the operator of the verdict (confirmed, rejected); null for a search's status")
    verdict_at: str | None = Field(description="when the verdict was given (UTC)")
    reason: str | None = Field(description="why the operator found no valid attitude (rejected)")
    search_id: int | None = Field(description="the newest search (null: never searched)")
    method: str | None = Field(description="that search's method")
    start: str = Field(description="time of the first snapshot (UTC)")
    end: str = Field(description="time of the last snapshot (UTC)")
    epoch: str = Field(description="time of the attitude: the reference snapshot's (the first snapshot's when the "
                                   "sequence was never searched)")
    n_snapshots: int
    rank: int | None = Field(description="the candidate plotted: the confirmed one, else rank 1 of an identified or "
                                         "ambiguous search; null: no attitude (no match, no valid attitude, not "
                                         "searched)")
    ra_deg: float | None
    dec_deg: float | None
    roll_deg: float | None
    sigma_ra_deg: float | None = Field(description="1-sigma of RA: the cross-boresight sigma / cos(Dec)")
    sigma_dec_deg: float | None
    sigma_roll_deg: float | None = Field(description="1-sigma of the roll (position angle from north)")
    rate_deg_s: float | None = Field(description="magnitude of the fitted body rate (null: no sequence fit)")
    sigma_rate_deg_s: float | None

    @classmethod
    def of(cls, entry) -> "TimelinePoint":
        """From an :class:`app.workflow.timeline.TimelineEntry`."""
        a = entry.attitude
        sigmas = (None, None, None) if a is None else a.radec_roll_sigma_deg()
        rate = (None, None) if a is None else a.rate_norm_deg_s()
        return cls(sequence=entry.seq_id, sequence_id=entry.sequence_id, filename=entry.filename,
                   status=entry.status, by=entry.by, verdict_at=utc_text(entry.verdict_at), reason=entry.reason,
                   search_id=entry.search_id, method=entry.method, start=utc_text(entry.start),
                   end=utc_text(entry.end), epoch=utc_text(entry.epoch), n_snapshots=entry.n_snapshots,
                   rank=None if a is None else a.rank, ra_deg=None if a is None else a.ra_deg,
                   dec_deg=None if a is None else a.dec_deg, roll_deg=None if a is None else a.roll_deg,
                   sigma_ra_deg=_rounded(sigmas[0], 9), sigma_dec_deg=_rounded(sigmas[1], 9),
                   sigma_roll_deg=_rounded(sigmas[2], 9), rate_deg_s=_rounded(rate[0], 9),
                   sigma_rate_deg_s=_rounded(rate[1], 9))


class TimelineFlagDocument(Document):
    """A gap, an overlap or a jump between two sequences of the timeline."""

    kind: Literal["gap", "overlap", "jump"]
    earlier: int = Field(description="archive id of the earlier sequence")
    later: int = Field(description="archive id of the later sequence")
    seconds: float = Field(description="the gap's or the overlap's length, or the time between a jump's epochs")
    angle_deg: float | None = Field(None, description="jump: the rotation the body rate does not explain")
    sigma_deg: float | None = Field(None, description="jump: the 1-sigma the attitudes' and the rate's "
                                                      "uncertainties allow it")
    chi2: float | None = Field(None, description="jump: chi-square of the rotation left over (3 degrees of freedom)")
    text: str = Field(description="what it is, in a sentence")


class TimelineDocument(Document):
    """A spacecraft's attitude timeline (``GET /api/spacecraft/{name}/timeline``), oldest first."""

    spacecraft: str
    start: str | None = Field(description="the range asked (first snapshot times in [start, end)); null: open")
    end: str | None
    limit: int
    total: int = Field(description="sequences of the spacecraft in the range (without a range: all with a time)")
    gap_s: float = Field(description="seconds without any sequence that make a gap")
    points: list[TimelinePoint]
    flags: list[TimelineFlagDocument]

    @classmethod
    def of(cls, timeline, texts: list[str]) -> "TimelineDocument":
        """From an :class:`app.workflow.timeline.Timeline` and its flags' sentences."""
        ids = [e.seq_id for e in timeline.entries]
        return cls(spacecraft=timeline.spacecraft, start=utc_text(timeline.start), end=utc_text(timeline.end),
                   limit=timeline.limit, total=timeline.total, gap_s=timeline.gap_s,
                   points=[TimelinePoint.of(e) for e in timeline.entries],
                   flags=[TimelineFlagDocument(kind=f.kind, earlier=ids[f.earlier], later=ids[f.later],
                                               seconds=round(f.seconds, 3),
                                               angle_deg=None if f.angle_rad is None else _rounded(
                                                   math.degrees(f.angle_rad), 9),
                                               sigma_deg=None if f.sigma_rad is None else _rounded(
                                                   math.degrees(f.sigma_rad), 9),
                                               chi2=_rounded(f.chi2, 3), text=text)
                          for f, text in zip(timeline.flags, texts)])
