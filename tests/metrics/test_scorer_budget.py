"""The motion scorer within a frame budget: references kept as parameters and their points in a bounded
least-recently-used cache, pairs posed and scored a chunk at a time, the same numbers as scoring at once."""
from __future__ import annotations

import numpy as np
import pytest
from test_scorer import clips, motion  # noqa: F401 - the four toy clips fixture and its motion helper

from m3t.metrics.scorer import REFERENCE_FRAMES, MotionPair, MotionScorer


def registered(body, toy: list, frame_budget: int = REFERENCE_FRAMES) -> MotionScorer:
    """A scorer holding the references of the ``clips`` fixture's ``toy`` clips (9, 5, 4 and 8 frames)."""
    scorer = MotionScorer(body, frame_budget=frame_budget)
    ident = body.default_identity().numpy()
    for cid, _, _, ref in toy:
        scorer.reference(cid, ref, ident)
    return scorer


def pairs_of(body, toy: list, ids: list[str] | None = None) -> list[MotionPair]:
    """The pairs of ``toy`` clips (those of ``ids``), scored against their stored references."""
    ident = body.default_identity().numpy()
    return [MotionPair(cid, group, pred, ident) for cid, group, pred, _ in toy if ids is None or cid in ids]


@pytest.mark.parametrize("frame_budget", [3, 12, 25])
def test_a_small_budget_scores_exactly_as_scoring_at_once(body, clips, frame_budget):  # noqa: F811
    """3: every pair a chunk alone, no reference kept; 12 and 25: chunks of several pairs, some references kept.
    A pair with its own reference and the empty prediction of "b" are scored alike."""
    ident = body.default_identity().numpy()
    given = MotionPair("given", "toy/ASL", motion(body, 6, 8), ident, reference=motion(body, 7, 9))
    pairs = [*pairs_of(body, clips)[:2], given, *pairs_of(body, clips)[2:]]
    at_once = registered(body, clips).score(pairs)
    budgeted = registered(body, clips, frame_budget)
    for _ in range(2):  # the second time from the cache where it holds the reference
        scores = budgeted.score(pairs)
        assert scores.per_clip == at_once.per_clip
        assert scores.overall == at_once.overall and scores.groups == at_once.groups
        assert list(scores.groups) == ["toy/DGS", "toy/ASL", "toy/CSL"]
        assert scores.empty_rate == at_once.empty_rate == 0.2
        assert scores.summary == at_once.summary
        assert budgeted.cached_frames <= frame_budget


def test_the_cache_holds_at_most_the_budget_evicting_the_least_recently_used(body, clips):  # noqa: F811
    frames = {"a": 9, "b": 5, "c": 4, "d": 8}
    scorer = registered(body, clips, frame_budget=12)
    assert scorer.cached == () and scorer.cached_frames == 0  # registering poses nothing
    # "c" used after "d": "d" is the least recently used and goes first for "b"
    for ids, cached in ((["a"], ("a",)), (["b"], ("b",)), (["c", "d"], ("c", "d")), (["c"], ("d", "c")),
                        (["b"], ("c", "b"))):
        scorer.score(pairs_of(body, clips, ids))
        assert scorer.cached == cached
        assert scorer.cached_frames == sum(frames[c] for c in cached) <= 12
    # a score never evicts a clip it scores: those kept stay, those that do not fit ("a", "d") are posed, not kept
    scorer.score(pairs_of(body, clips))
    assert scorer.cached == ("b", "c") and scorer.cached_frames == 9


def test_a_reference_rescored_after_eviction_is_posed_again_to_the_same_metrics(body, clips):  # noqa: F811
    scorer = registered(body, clips, frame_budget=10)
    first = scorer.score(pairs_of(body, clips, ["a"])).per_clip
    assert scorer.cached == ("a",)
    scorer.score(pairs_of(body, clips, ["d"]))  # 9 + 8 frames > 10: "a" goes
    assert scorer.cached == ("d",)
    assert scorer.score(pairs_of(body, clips, ["a"])).per_clip == first
    longer = registered(body, clips, frame_budget=3)  # every reference longer than the budget: used, never kept
    assert longer.score(pairs_of(body, clips, ["a"])).per_clip == first and longer.cached == ()


def test_replacing_a_reference_drops_its_cached_points(body, clips):  # noqa: F811
    scorer = registered(body, clips, frame_budget=20)
    ident = body.default_identity().numpy()
    pair = pairs_of(body, clips, ["a"])
    before = scorer.score(pair).per_clip[0].metrics
    scorer.reference("a", clips[3][3], ident)  # now "d"'s reference (8 frames)
    assert scorer.cached == ()
    after = scorer.score(pair).per_clip[0].metrics
    assert after != before
    given = MotionScorer(body).score([MotionPair("a", "g", clips[0][2], ident, reference=clips[3][3])])
    assert after == given.per_clip[0].metrics
    assert scorer.cached_frames == 8


def test_unknown_clips_bad_references_and_budgets_are_named_before_any_work(body, clips):  # noqa: F811
    scorer = registered(body, clips, frame_budget=3)
    ident = body.default_identity().numpy()
    with pytest.raises(KeyError, match=r"clip 'zz'.*MotionScorer\.reference.*\(2 clips lack one\)"):
        scorer.score([*pairs_of(body, clips, ["a"]), MotionPair("zz", "g", clips[0][2], ident),
                      MotionPair("yy", "g", clips[0][2], ident)])
    short = {k: v for k, v in clips[0][3].items() if k != "face"}
    with pytest.raises(ValueError, match=r"reference of clip 'e'.*lack modalities \['face'\]"):
        scorer.reference("e", short, ident)
    with pytest.raises(ValueError, match=r"reference of clip 'e': identity of shape \(3,\)"):
        scorer.reference("e", clips[0][3], ident[:3])
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="frame_budget: expected a positive number of frames"):
            MotionScorer(body, frame_budget=bad)


def test_a_bad_pair_in_a_later_chunk_is_named_by_its_clip_and_place(body, clips):  # noqa: F811
    scorer = registered(body, clips, frame_budget=3)
    pairs = pairs_of(body, clips)
    broken = {k: v.copy() for k, v in pairs[2].prediction.items()}
    broken["body"][2] = np.nan
    pairs[2] = MotionPair("c", "toy/CSL", broken, pairs[2].identity)
    with pytest.raises(ValueError, match=r"clip 'c': pair 2, region 'body', prediction: non-finite values"):
        scorer.score(pairs)


def test_one_progress_bar_over_every_chunk(body, clips, capfd):  # noqa: F811
    scorer = registered(body, clips, frame_budget=3)
    capfd.readouterr()
    scorer.score(pairs_of(body, clips))
    assert "dtw" not in capfd.readouterr().err, "no progress bar unless asked"
    scorer.score(pairs_of(body, clips), progress=True)
    err = capfd.readouterr().err
    assert "4/4" in err and "1/1" not in err


def test_the_smlm_evaluator_scores_within_a_budget_as_without(body, clips):  # noqa: F811
    from m3t.corpora.clip import Clip
    from m3t.shards.schema import FittedClip
    from m3t.smlm.data import Example
    from m3t.smlm.evaluate import SMLMEvaluator

    ident = body.default_identity().numpy()
    examples = [Example(cid, group.split("/")[1], "text", np.zeros(1, np.int64), np.zeros((1, 4), np.int64))
                for cid, group, _, _ in clips]
    references = {cid: FittedClip(Clip(cid, "toy", "test", group.split("/")[1], "s1", "text", "G", f"{cid}.npz", 25.0),
                                  "k", ref, ident, {}, {}, body.name) for cid, group, _, ref in clips}
    generated = {cid: pred for cid, _, pred, _ in clips}
    default = SMLMEvaluator(body, {}, None, examples, references)
    budgeted = SMLMEvaluator(body, {}, None, examples, references, frame_budget=3)
    assert default.scorer.frame_budget == REFERENCE_FRAMES and budgeted.scorer.frame_budget == 3
    expected = default.score_motion(generated)
    assert budgeted.score_motion(generated) == expected
    assert budgeted.scorer.cached == () and default.scorer.cached == tuple(references)
    assert [c.group for c in expected.per_clip] == ["toy/DGS", "toy/DGS", "toy/CSL", "toy/CSL"]


@pytest.mark.parametrize("frame_budget", [3, REFERENCE_FRAMES])
def test_references_left_in_their_shards_score_as_references_in_memory(body, clips, tmp_path, monkeypatch,  # noqa: F811
                                                                       frame_budget):
    """SplitReferences (parameters read from the shard's row groups when posed) against the same FittedClips held
    in memory: the same figures, in the process and on the executor path's pairs; nothing posed at registration."""
    import m3t.shards.io as shard_io
    from m3t.corpora.clip import Clip
    from m3t.shards.io import write_shard
    from m3t.shards.references import SplitReferences
    from m3t.shards.schema import FittedClip
    from m3t.smlm.data import Example
    from m3t.smlm.evaluate import SMLMEvaluator

    ident = body.default_identity().numpy()
    examples = [Example(cid, group.split("/")[1], "text", np.zeros(1, np.int64), np.zeros((1, 4), np.int64))
                for cid, group, _, _ in clips]
    fitted = [FittedClip(Clip(cid, "toy", "test", group.split("/")[1], "s1", "text", "G", f"{cid}.npz", 25.0),
                         "k", {k: np.asarray(v, np.float32) for k, v in ref.items()}, ident, {}, {}, body.name)
              for cid, group, _, ref in clips]
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", 10)  # 9 | 5 4 | 8 frames: three row groups
    (tmp_path / "toy").mkdir()
    write_shard(tmp_path / "toy" / "test.parquet", fitted, body.layout)
    stored = SplitReferences([tmp_path / "toy"], "test")
    generated = {cid: pred for cid, _, pred, _ in clips}
    in_memory = SMLMEvaluator(body, {}, None, examples, {f.clip.id: f for f in fitted}, frame_budget=frame_budget)
    from_shards = SMLMEvaluator(body, {}, None, examples, stored, frame_budget=frame_budget)
    assert stored._group is None, "registering read no parameters"
    expected = in_memory.score_motion(generated)
    for _ in range(2):  # the second time from the cache where it holds the reference
        assert from_shards.score_motion(generated) == expected
    assert from_shards.scorer.cached == in_memory.scorer.cached


def test_a_reference_read_on_demand_is_checked_when_it_is_read(body, clips):  # noqa: F811
    ident = body.default_identity().numpy()
    _, group, pred, ref = clips[0]
    scorer = MotionScorer(body)
    scorer.reference_on_demand("a", 9, ident, lambda: ref)
    assert scorer.score([MotionPair("a", group, pred, ident)]) == registered(body, clips[:1]).score(
        [MotionPair("a", group, pred, ident)])
    scorer.reference_on_demand("a", 8, ident, lambda: ref)  # replaced: now announced one frame short
    with pytest.raises(ValueError, match=r"reference of clip 'a': 9 frames read, 8 announced; its shard changed"):
        scorer.score([MotionPair("a", group, pred, ident)])
    scorer.reference_on_demand("a", 9, ident, lambda: {k: v[:, :-1] for k, v in ref.items()})
    with pytest.raises(ValueError, match=r"reference of clip 'a': "):
        scorer.score([MotionPair("a", group, pred, ident)])
    with pytest.raises(ValueError, match=r"reference of clip 'b': identity of shape \(2,\)"):
        scorer.reference_on_demand("b", 9, np.zeros(2), lambda: ref)
