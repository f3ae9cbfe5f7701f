"""The SGSA / PT training target and batches (:mod:`m3t.sgsa.data`) and which runs the SGSA tables show
(:mod:`m3t.sgsa.table`), on hand-made values: the counter column is ``(t + 1) / U`` (the last frame 1), a batch
feeds the zero frame then the target shifted by one, and a table row is the newest finished run of each
(variant, seed). Written to pin behaviours that mutation testing found unchecked."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from m3t.experiment import RunRecord
from m3t.sgsa.config import SGSAConfig
from m3t.sgsa.data import (
    Sample,
    collate,
    counter_column,
    make_samples,
    text_tokens,
    with_counter,
)
from m3t.sgsa.model import SGSAOutput
from m3t.sgsa.table import (
    adjacency_table,
    counter_line,
    cross_table,
    layers_table,
    row_values,
)
from m3t.sgsa.train import losses
from m3t.vocabulary import text_vocabulary


def test_the_counter_target_is_the_progress_of_each_frame_and_the_last_frame_has_one():
    assert counter_column(4).tolist() == [0.25, 0.5, 0.75, 1.0]  # exact in float32 (powers of two)
    assert counter_column(1).tolist() == [1.0] and counter_column(0).shape == (0,)
    assert counter_column(3).dtype == np.float32
    coords = np.arange(6, dtype=np.float64).reshape(2, 3)
    target = with_counter(coords)
    assert target.dtype == np.float32 and target.shape == (2, 4)
    assert target[:, :3].tolist() == coords.tolist() and target[:, 3].tolist() == [0.5, 1.0]


def sample(frames: int, text: tuple[int, ...], glosses: tuple[int, ...] = (), value: float = 1.0) -> Sample:
    return Sample(clip=None, text_ids=text, gloss_ids=glosses,
                  target=with_counter(np.full((frames, 2), value, dtype=np.float32)))


def test_a_batch_pads_and_feeds_the_zero_frame_then_the_target_shifted_by_one():
    vocab = text_vocabulary([["a", "b", "c"]])  # <pad> = 0
    batch = collate([sample(2, (4, 5), (1, 2, 3), 7.0), sample(3, (6,), (), 9.0)], vocab)
    assert batch.text_ids.tolist() == [[4, 5], [6, 0]] and batch.text_mask.tolist() == [[True, True], [True, False]]
    assert batch.frame_mask.tolist() == [[True, True, False], [True, True, True]]
    assert batch.target.shape == (2, 3, 3)
    assert batch.target[0, :, 0].tolist() == [7.0, 7.0, 0.0] and batch.target[0, :, 2].tolist() == [0.5, 1.0, 0.0]
    assert torch.equal(batch.frames_in[:, 0], torch.zeros(2, 3))  # the start frame: all zeros, counter 0
    assert torch.equal(batch.frames_in[:, 1:], batch.target[:, :-1])  # then frame t - 1 predicts frame t
    assert batch.glosses.tolist() == [[1, 2, 3], [0, 0, 0]] and batch.gloss_lengths.tolist() == [3, 0]


def clip(clip_id: str, text: str, frames: int, gloss: str = "") -> SimpleNamespace:
    meta = SimpleNamespace(id=clip_id, split="train", text=text, language="ASL-SYN", gloss=gloss, label=None,
                           corpus="c")
    return SimpleNamespace(clip_id=clip_id, fitted=SimpleNamespace(clip=meta), coords=np.ones((frames, 2), dtype=np.float32))


def test_samples_skip_unusable_clips_with_their_reason_and_cut_long_ones_where_allowed():
    cfg = SGSAConfig(max_text_tokens=3, max_frames=4)
    vocab = text_vocabulary([text_tokens("one two three four", "ASL-SYN")])
    clips = [clip("ok", "one two", 6), clip("empty", "  ", 3), clip("still", "one", 0),
             clip("long", "one two three four", 2)]
    train = make_samples(clips, vocab, None, cfg, training=True)
    assert [s.clip_id for s in train.samples] == ["ok"]
    assert [(s["clip_id"], s["reason"]) for s in train.skipped] == [
        ("empty", "empty text"), ("still", "no frames"), ("long", "5 text tokens; sgsa.max_text_tokens is 3")]
    ok = train.samples[0]
    assert ok.text_ids == tuple(vocab.encode(["<2ASL-SYN>", "one", "two"])) and ok.gloss_ids == ()
    assert ok.target.shape == (4, 3) and ok.target[:, 2].tolist() == [0.25, 0.5, 0.75, 1.0]  # cut, then counted
    assert (train.cut_frames, train.cut_text) == (1, 0)
    evaluation = make_samples(clips, vocab, None, cfg, training=False)  # longer text is cut, longer clips kept
    assert [s.clip_id for s in evaluation.samples] == ["ok", "long"]
    assert [s["clip_id"] for s in evaluation.skipped] == ["empty", "still"]
    assert (evaluation.cut_frames, evaluation.cut_text) == (0, 1)
    assert len(evaluation.samples[0].target) == 6 and len(evaluation.samples[1].text_ids) == 3


# ------------------------------------------------------------------------------------------ tables
def record(run_id: str, layers: int | None, adjacency: int | None, seed: int, bleu4: float, status: str = "FINISHED",
           counter: str = "predicted", systems=("pt", "sgsa", "smlm", "ground_truth")) -> RunRecord:
    metrics = {}
    for system in systems:
        for split in ("dev", "test"):
            metrics[f"{system}/{split}/bt/slt/ASL-SYN/bleu4"] = bleu4
            metrics[f"{system}/{split}/bt/slt/DGS-SYN/bleu4"] = bleu4 + 2.0
            metrics[f"{system}/{split}/dtw_jpe_mean_m"] = bleu4 / 1000.0
    params = {} if layers is None else {"sgsa.decoder_layers": str(layers), "sgsa.temporal_adjacency": str(adjacency)}
    return RunRecord(run_id, "evaluate-sgsa", 0, status, params, metrics, None, {"seed": str(seed), "counter": counter})


def cell(table: str, first: str, column: int) -> str:
    row = next(line for line in table.splitlines() if line.startswith(f"| {first} |"))
    return row.split(" | ")[column].strip(" |")


def test_a_row_is_the_newest_finished_run_of_each_seed_and_the_mean_over_seeds():
    # newest first, as fetch_runs gives them: the failed newest run and the older run of seed 0 are not shown
    records = [record("failed", 2, 0, 0, 90.0, status="FAILED"), record("new0", 2, 0, 0, 10.0),
               record("old0", 2, 0, 0, 50.0), record("new1", 2, 0, 1, 20.0)]
    tab1 = layers_table(records)
    # seed 0: (10 + 12) / 2 = 11 over the languages, seed 1: 21; mean 16; DTW-JPE (10 + 20) / 2 mm
    assert cell(tab1, "2", 1) == "16.00" and cell(tab1, "2", 6) == "15.00" and cell(tab1, "2", 13) == "2"
    assert cell(tab1, "0 (PT, standard SA)", 1) == "16.00"  # PT too: newest finished per seed
    values, runs = row_values([record("x", 2, 0, 0, 4.0)], "sgsa")
    assert runs == 1 and values["dev/bleu4"] == pytest.approx(5.0) and values["test/dtw_jpe_mm"] == pytest.approx(4.0)
    assert "bleu3" not in {k.split("/")[1] for k in values}  # a column no run logged stays empty


def test_tab1_shows_only_infinite_adjacency_and_tab2_the_l_with_most_variants():
    records = [record("a", 2, 0, 0, 10.0), record("b", 3, 1, 0, 20.0), record("c", 3, 0, 0, 30.0),
               record("d", 2, 1, 0, 40.0), record("e", 3, 2, 0, 50.0)]
    tab1 = layers_table(records)
    assert cell(tab1, "2", 1) == "11.00" and cell(tab1, "3", 1) == "31.00"  # N = inf only (0 = inf)
    tab2 = adjacency_table(records)  # L = 3 has three variants, L = 2 two
    assert "L = 3" in tab2 and cell(tab2, "inf", 1) == "31.00" and cell(tab2, "1", 1) == "21.00"
    assert cell(tab2, "2", 1) == "51.00"
    lines = [line.split(" | ")[0].strip("| ") for line in tab2.splitlines() if line.startswith("| ")][1:]
    assert lines == ["inf", "1", "2"]  # inf first, then N ascending
    assert "L = 2" in adjacency_table(records, layers=2) and cell(adjacency_table(records, layers=2), "1", 1) == "41.00"
    tied = [record("a", 2, 0, 0, 10.0), record("b", 3, 0, 0, 20.0)]
    assert "L = 3" in adjacency_table(tied)  # a tie goes to the larger L


def test_the_cross_table_shows_the_newest_runs_variant_and_says_how_lengths_were_decided():
    records = [record("newest", 3, 1, 0, 10.0), record("other", 2, 0, 0, 70.0), record("same", 3, 1, 1, 30.0)]
    tab3 = cross_table(records)
    assert "(L=3, N=1)" in tab3
    assert cell(tab3, "Skeletal Graph Self-Attention (L=3, N=1)", 1) == "21.00"  # seeds 0 and 1 of L=3, N=1
    assert cell(tab3, "M3T SMLM (posed into the skeleton)", 1) == "11.00"  # the newest run only
    assert "N=inf" in cross_table([record("n", 2, 0, 0, 1.0)])
    assert cross_table([record("f", 2, 0, 0, 1.0, status="FAILED")]).startswith("no finished evaluate-sgsa run")
    assert counter_line([]) == "Lengths: no run."
    assert counter_line([record("a", 2, 0, 0, 1.0, counter="ground_truth")]) == (
        "Lengths: ground-truth lengths (the true counter fed back; parity with published PT numbers).")
    both = counter_line([record("a", 2, 0, 0, 1.0), record("b", 2, 0, 0, 1.0, counter="ground_truth")])
    assert both.endswith("(runs of both modes pooled: rerun one mode).")


class Frozen:
    """A stand-in model that predicts all-zero frames (and no glosses), recording the frames it was fed."""

    def __call__(self, text_ids, text_mask, frames_in, frame_mask):
        self.fed = frames_in
        return SGSAOutput(torch.zeros_like(frames_in), None)


def test_the_loss_is_the_mse_of_real_frames_plus_the_weighted_counter_error():
    vocab = text_vocabulary([["a"]])
    batch = collate([sample(2, (4,), value=1.0), sample(1, (4,), value=2.0)], vocab)
    # errors of the zero prediction on the real frames: [-1, -1, -0.5], [-1, -1, -1], [-2, -2, -1] (the padded
    # frame of the second clip is left out)
    plain, err = losses(Frozen(), batch, gloss_weight=0.0)
    assert err.tolist() == [[-1.0, -1.0, -0.5], [-1.0, -1.0, -1.0], [-2.0, -2.0, -1.0]]
    assert set(plain) == {"loss", "skeleton_loss"}
    assert float(plain["skeleton_loss"]) == pytest.approx(14.25 / 9) and float(plain["loss"]) == pytest.approx(14.25 / 9)
    weighted, _ = losses(Frozen(), batch, gloss_weight=0.0, counter_weight=2.0)
    assert float(weighted["counter_loss"]) == pytest.approx(2.25 / 3)  # (0.25 + 1 + 1) / 3
    assert float(weighted["loss"]) == pytest.approx(14.25 / 9 + 2.0 * 0.75)
    model = Frozen()
    losses(model, batch, 0.0, noise_std=torch.ones(3))
    assert torch.equal(model.fed[..., -1], batch.frames_in[..., -1])  # the counter is never perturbed
    assert not torch.equal(model.fed[..., :-1], batch.frames_in[..., :-1])


def test_a_split_without_clips_scores_an_infinite_selection_figure():
    """No clip to score (a dev split emptied by the length filters): the selection figure is +inf, so such a
    checkpoint is never kept as the best, and no other figure is invented."""
    from m3t.body.skeleton import body_graph
    from m3t.sgsa.evaluate import MEAN_DTW, SELECTION_METRIC, score_production

    report = score_production([], {}, body_graph(), 100)
    assert report.summary[MEAN_DTW] == report.summary[SELECTION_METRIC] == float("inf")
    assert "length_penalty" not in report.summary and report.per_clip == []
