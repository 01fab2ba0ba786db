"""The tunable parameters of a search (:class:`SearchOptions`), each default with its reason."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SearchOptions:
    """Tunable parameters of a search, with the reasoning for each default.

    FUSE's star identification rules (seed 001, Table 3) map onto these:
    ``min_pair_ang`` -> :attr:`min_pair_separation_px`, ``max_pair_ang`` -> the
    index's longest edge, ``pair_ang_tol`` -> :attr:`edge_tolerance_px`,
    ``addl_mtch_tol`` -> :attr:`match_tolerance_px`, ``max_roll`` ->
    :attr:`max_roll_change_deg` (tracking from a prior), ``min_mch`` ->
    :attr:`min_matches`, ``des_mch`` -> :attr:`early_stop_matches`, and the
    time-out -> :attr:`timeout_s`.
    """

    #: Edge-length window: this many pixels of systematic error (centroiding,
    #: distortion) plus 4 sigma of the two points' random error.
    edge_tolerance_px: float = 1.0
    #: Pattern points closer than this never form an edge (no usable direction;
    #: maybe one star reported twice).
    min_pair_separation_px: float = 2.0
    #: A pattern point matches a star within max(this, 5 sigma) pixels.
    match_tolerance_px: float = 1.5
    #: Fewest matched stars for a candidate to be reported (FUSE asks 4; with
    #: the false-match probability judging significance, 3 may be shown).
    min_matches: int = 3
    #: Tracking: a solution whose roll differs from the prior's by more than
    #: this is not accepted as "identified".
    max_roll_change_deg: float = 5.0
    #: Stars down to the camera's limiting magnitude plus this margin can be
    #: in the pattern (brightness is unreliable and detection is noisy).
    mag_margin: float = 0.75
    #: Use at most this many pattern points, the brightest.
    max_points: int = 16
    #: Distinct candidates returned for the operator to step through (the
    #: seed's Next/Prev: past the first few, alternatives are chance fits).
    max_candidates: int = 6
    #: Hypotheses refined (in order of promise) to find those candidates.
    max_refinements: int = 16
    #: Status "identified" needs a best false-match probability at most this ...
    identified_probability: float = 1e-6
    #: ... and no rival: another distinct candidate at or below this
    #: probability, with an RMS residual within this factor of the best's, and
    #: at most this many times as likely to be chance as the best (the odds
    #: of the two explanations: a 15-star match at 1e-60 is not put in doubt
    #: by a 3-star coincidence at 1e-4, a 4-star match at 1e-8 is).
    rival_probability: float = 1e-3
    rival_rms_factor: float = 3.0
    rival_odds: float = 1e6
    #: No candidate at or below this false-match probability: "no_match".
    no_match_probability: float = 0.01
    #: Stop generating hypotheses once a refined hypothesis matches this many
    #: points (or all of them) and this fraction of them, and at least this
    #: many edges were tried.  The fraction matters in dense fields: a slightly
    #: wrong attitude can catch 6 of 30 points, the right one catches nearly all.
    early_stop_matches: int = 6
    early_stop_fraction: float = 0.5
    early_stop_edges: int = 1
    #: Hypotheses refined right after each batch of edges.
    refine_per_batch: int = 3
    #: Wall-clock budget of one search, seconds.
    timeout_s: float = 5.0
    #: ... and its count of hypotheses, which bounds it the same way on a loaded machine: a pattern that fits
    #: nowhere tries 52,000-92,000 against the default index (10 random points, 20 deg camera; 90,000-136,000
    #: before the focal scan and the Delaunay edges), but a narrow field against the Hp 8 index 600,000 and
    #: more (5 s) before the time-out stopped it.
    max_hypotheses: int = 300_000
    #: Planets are labelled when an unmatched point lies within this many pixels.
    planet_tolerance_px: float = 3.0
    #: When the declared camera does not settle the answer, search focal lengths within the camera's
    #: declared tolerance (real focal lengths are known to 1-5 %: app.identification.optics).
    search_focal_length: bool = True
    #: ... trying this many pattern features (edges) at each searched focal length (bright pairs: at all of
    #: them at once, app.identification.focal_scan): at the right one the first sure edges settle the answer,
    #: and a full search at every step would cost a dozen searches.
    focal_search_features: int = 3
    #: ... and this many where the focal length is known only roughly, its tolerance wider than a calibrated
    #: camera's (app.camera.DEFAULT_FOCAL_LENGTH_TOLERANCE, 5 %): a field of view given by hand or read from a
    #: file's header (app.frames.assemble.FOV_FOCAL_TOLERANCE, 10 % and more).  The declared value is then the
    #: middle of a range, no likelier than its neighbours, so the other focal lengths get as many features as
    #: the declared one gets first (declared_features_first).  On the real frames given a field of view 5 % off,
    #: a 6 deg field whose brightest sources are not Hipparcos's brightest (may8-gain40-img7) settles on its
    #: 7th edge: with 3 it was no match at every field of view but the exact one (real frames 24/23/23/23 ->
    #: 25/25/24/24 of 25 identified, none wrong).  A calibrated camera keeps 3: frames that match nothing (the
    #: Earth, noise) would take half as long again with 7 (20.9 -> 31.6 ms a frame of 10 random points).
    rough_focal_search_features: int = 7
    #: ... and checking at most this many hypotheses at the other focal lengths (a phase that starts within
    #: the count runs whole): a wrong focal length is usually found within a few steps (40 single snapshots of
    #: the 20 deg camera 5 % off: 15,000-65,000 hypotheses in all, 0.07-0.43 s of CPU), while a pattern that
    #: fits nowhere (the Earth, noise) tries every step (10 random points: 90,000-136,000).  It was measured
    #: 30,000: Earth-in-view snapshots 2-4x faster (p95 690 -> 280 ms on the 20 deg camera) with every row of
    #: the identification and camera benchmarks unchanged, but one of 100 snapshots 5 % off (bench --suite
    #: peer) then went unidentified: its triangles fit no focal length and the stepped search found it after
    #: 87,800 hypotheses.  A count, not seconds: the same data get the same answer on a loaded machine (a
    #: wall-clock budget left frames unsolved under load).  The focal scan tries each catalogue pair of an
    #: edge once (or, when it caught a third star, at the few focal lengths of its window): 10 random points
    #: now try ~30,000 there, so the bound binds the triangle features' stepped search, not the bright pairs'.
    focal_search_max_hypotheses: int = 200_000
    #: The declared camera tries this many features before the other focal lengths are searched (and
    #: the rest after them): 7 is the first three batches (1 + 2 + 4 edges), past which an exact camera
    #: rarely needs to go.
    declared_features_first: int = 7
    #: Fit the optics (focal length, k1 from 6 stars) with the attitude of every credible candidate;
    #: the fitted camera replaces the declared one only where the data ask for it.
    fit_optics: bool = True
    #: The sky position of the image's centre pixel for every credible candidate (a frame's reference
    #: point, astrometry.net's: an optics fit on every source, ~0.7 ms a single snapshot); a caller that
    #: needs only the attitude (the boresight) may leave it out.
    image_centre: bool = True
