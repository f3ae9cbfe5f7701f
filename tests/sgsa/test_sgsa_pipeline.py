"""The skeletal production path end to end on tiny fitted shards: the skeleton judge, PT + SGSA training with
resume, counter-decoded evaluation through the shared scorers and judge, the Prefect flow and the tables."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from float_order import assert_close_json, assert_close_numbers, assert_close_weights

from m3t.backtranslation.pipeline import SkeletonInput, run_train_backtranslation
from m3t.body.skeleton import body_graph
from m3t.config import load_params
from m3t.experiment import RunRecord
from m3t.sgsa.checkpoint import load_sgsa
from m3t.sgsa.config import SGSAConfig, SGSATrainConfig
from m3t.sgsa.data import collate, make_samples, vocabularies
from m3t.sgsa.pipeline import run_evaluate, run_train
from m3t.sgsa.table import adjacency_table, cross_table, layers_table, sweep_settings
from m3t.sgsa.train import losses, train_sgsa
from m3t.shards.io import read_split
from m3t.shards.skeletons import skeleton_clips
from m3t.training_jobs import worker_split

ROOT = Path(__file__).resolve().parents[2]


def tiny_params(shards_dir: Path, root: Path, **sections):  # noqa: F811
    overrides = {"data": {"shards_root": str(shards_dir.parent), "tokens_root": str(root / "tokens"),
                          "models_dir": str(root / "models"), "generated_dir": str(root / "gen"),
                          "metrics_dir": str(root / "metrics")},
                 "sgsa_train": {"cache_dir": str(root / "cache")},
                 "backtranslation_train": {"cache_dir": str(root / "cache-bt")}, **sections}
    return load_params(ROOT / "params.yaml", preset="tiny", overrides=overrides)


@pytest.fixture(scope="module")
def trained(shards_dir, body, tmp_path_factory):  # noqa: F811
    root = tmp_path_factory.mktemp("sgsa")
    params = tiny_params(shards_dir, root)
    graph = body_graph()
    run_train_backtranslation(params.backtranslation, params.backtranslation_train, params.data, progress=False,
                              skeleton=SkeletonInput(body, graph))
    report = run_train(params.sgsa, params.sgsa_train, body, params.data, progress=False)
    return params, report


def test_train_writes_both_systems_with_self_describing_checkpoints(trained):
    params, report = trained
    out = params.data.sgsa_dir
    assert sorted(p.name for p in out.glob("*.pt")) == ["pt.pt", "sgsa.pt"]
    pt, sgsa = load_sgsa(out / "pt.pt"), load_sgsa(out / "sgsa.pt")
    assert pt.model.cfg.decoder_layers == 0 and pt.model.cfg.variant == "PT"
    assert sgsa.model.cfg.decoder_layers == params.sgsa.decoder_layers and sgsa.graph == body_graph()
    assert sgsa.model.dims.width == body_graph().width + 1 == report["skeleton_width"]
    assert report["pt/parameters"] > 0 and report["sgsa/parameters"] > 0
    assert json.loads((out / "metrics.json").read_text())["train_clips"] == report["train_clips"] > 0


def test_a_checkpoint_of_the_older_decoder_says_to_retrain(trained, tmp_path):
    params, _ = trained
    payload = torch.load(params.data.sgsa_dir / "sgsa.pt", weights_only=True)
    torch.save({**payload, "format": "m3t-sgsa-v1"}, tmp_path / "old.pt")
    with pytest.raises(ValueError, match=r"old\.pt: an SGSA / PT checkpoint of an older decoder .*dvc repro train-sgsa"):
        load_sgsa(tmp_path / "old.pt")
    torch.save({**payload, "format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not an m3t SGSA / PT checkpoint"):
        load_sgsa(tmp_path / "other.pt")


def test_evaluate_scores_every_system_with_the_same_judge(trained, body):
    params, _ = trained
    summary = run_evaluate(params.sgsa, params.sgsa_evaluate, body, params.data, params.backtranslation,
                           progress=False)
    for system in ("pt", "sgsa"):
        for split in params.sgsa_evaluate.splits:
            at = lambda key: summary[f"{system}/{split}/{key}"]  # noqa: E731
            assert np.isfinite(at("dtw_jpe_mean_m"))
            assert at("mean_frames") >= 1
            # the selection figure: DTW-JPE times the mean length penalty max(U / U_ref, U_ref / U) >= 1
            assert at("length_penalty") >= 1 and at("dtw_jpe_mean_x_length_m") == \
                pytest.approx(at("dtw_jpe_mean_m") * at("length_penalty"))
            assert 0 <= at("length_within_25") <= 1 and 0 <= at("stopped_rate") <= 1 and at("length_ratio_median") > 0
            assert f"{system}/{split}/bt/slt_bleu4" in summary
    # the ground truth goes through the same judge; no generate-smlm output here, so no SMLM row
    assert "ground_truth/test/bt/slt_bleu4" in summary and not any(k.startswith("smlm/") for k in summary)
    out = params.data.metrics("sgsa")
    rows = (out / "per_clip.csv").read_text().splitlines()
    assert rows[0].startswith("system,split,clip_id")
    assert len(rows) - 1 == 2 * sum(summary[f"{s}/clips"] for s in params.sgsa_evaluate.splits)
    assert (out / "backtranslation.csv").read_text().startswith("system,split,clip_id")
    assert (out / "attention.png").stat().st_size > 0
    videos = sorted((out / "videos").glob("*.mp4"))
    assert len(videos) == params.sgsa_evaluate.render_clips
    # every produced clip (U >= 1 frames) of every trained system as a skeleton .pose: the graph's joints
    from pose_format import Pose

    for system in ("pt", "sgsa"):
        poses = sorted((out / "pose" / system).glob("*.pose"))
        assert len(poses) == sum(summary[f"{split}/clips"] for split in params.sgsa_evaluate.splits)
        assert tuple(Pose.read(poses[0].read_bytes()).header.components[0].points) == body_graph().joints


def test_ground_truth_counter_gives_the_reference_length(trained, body):
    params, _ = trained
    cfg = dataclasses.replace(params.sgsa_evaluate, counter="ground_truth", backtranslate=False, render_clips=0,
                              splits=("test",))
    summary = run_evaluate(params.sgsa, cfg, body, params.data, progress=False)
    for system in ("pt", "sgsa"):
        assert summary[f"{system}/test/length_ratio"] == pytest.approx(1.0)
        assert summary[f"{system}/test/length_ratio_median"] == pytest.approx(1.0)
        assert summary[f"{system}/test/length_within_25"] == 1.0 and summary[f"{system}/test/length_penalty"] == 1.0


def samples_for(body, shards_dir, cfg):  # noqa: F811
    graph = body_graph()
    clips = skeleton_clips(body, read_split([shards_dir], "train"), graph)
    text_vocab, gloss_vocab = vocabularies(clips, cfg)
    return graph, text_vocab, gloss_vocab, make_samples(clips, text_vocab, gloss_vocab, cfg, training=True).samples


def test_noise_augmentation_leaves_the_counter_and_scales_with_the_error_std(body, shards_dir):  # noqa: F811
    cfg = SGSAConfig(encoder_width=16, encoder_ffn=32, encoder_heads=2, decoder_layers=1, decoder_heads=1, dropout=0.0)
    graph, text_vocab, gloss_vocab, samples = samples_for(body, shards_dir, cfg)
    from m3t.sgsa.checkpoint import build_model

    model = build_model(cfg, graph, text_vocab, gloss_vocab)
    batch = collate(samples[:2], text_vocab)
    seen = {}
    original = model.forward

    def spy(text_ids, text_mask, frames_in, frame_mask=None):
        seen["frames_in"] = frames_in
        return original(text_ids, text_mask, frames_in, frame_mask)

    model.forward = spy
    clean, _ = losses(model, batch, 0.0, None)
    assert torch.equal(seen["frames_in"], batch.frames_in)
    std = torch.full((graph.width + 1,), 0.5)
    torch.manual_seed(0)
    losses(model, batch, 0.0, std)
    noise = seen["frames_in"] - batch.frames_in
    assert torch.all(noise[..., -1] == 0), "the counter column must never be perturbed"
    assert noise[..., :-1].std().item() == pytest.approx(0.5, rel=0.1)


def test_noise_is_capped_at_the_coordinates_spread_so_it_cannot_feed_back_on_itself(body, shards_dir):  # noqa: F811
    """PT's rule (rate x last epoch's error std) grows without bound once noise raises the error; the cap holds each
    coordinate's noise std at ``noise_cap`` x its std over the train split's frames."""
    from m3t.sgsa.train import augmentation_std, noise_ceiling

    cfg = SGSAConfig()
    _, _, _, samples = samples_for(body, shards_dir, cfg)
    cpu = torch.device("cpu")
    frames = np.concatenate([s.target for s in samples]).astype(np.float64)
    ceiling = noise_ceiling(samples, 0.5, cpu)
    torch.testing.assert_close(ceiling, torch.as_tensor(0.5 * frames.std(0), dtype=torch.float32))
    assert noise_ceiling(samples, 0.0, cpu) is None  # no cap
    small, huge = 0.01 * ceiling, 100.0 * ceiling
    torch.testing.assert_close(augmentation_std(small, 5.0, ceiling, cpu), 5.0 * small)  # below the cap: PT's rule
    torch.testing.assert_close(augmentation_std(huge, 5.0, ceiling, cpu), ceiling)  # capped
    torch.testing.assert_close(augmentation_std(huge, 5.0, None, cpu), 5.0 * huge)  # noise_cap 0: PT's rule
    assert augmentation_std(None, 5.0, ceiling, cpu) is None and augmentation_std(small, 0.0, ceiling, cpu) is None
    # iterated, the capped rule stays bounded whatever the error does
    std = small
    for _ in range(10):
        std = augmentation_std(std * 3.0, 5.0, ceiling, cpu)  # errors 3x the noise: the uncapped rule grows 15x
    assert torch.all(std <= ceiling)


def test_a_killed_run_resumes_to_the_same_model(body, shards_dir, tmp_path):  # noqa: F811
    cfg = SGSAConfig(encoder_width=16, encoder_ffn=32, encoder_heads=2, decoder_layers=1, decoder_heads=1,
                     dropout=0.1)
    graph, text_vocab, gloss_vocab, samples = samples_for(body, shards_dir, cfg)
    train_cfg = SGSATrainConfig(epochs=4, batch_size=2, eval_every=2, device="cpu", noise_rate=5.0)

    def run(folder: Path, stop=None):
        return train_sgsa(cfg, train_cfg, graph, text_vocab, gloss_vocab, samples, samples[:1], "v", folder / "best.pt",
                          folder / "last.pt", progress=False, stop_after_epochs=stop)

    straight = run(tmp_path / "a")
    first = run(tmp_path / "b", stop=2)
    assert len(first.history) == 2
    resumed = run(tmp_path / "b")
    assert resumed.resumed_from_epoch == 2
    assert [r["train_loss"] for r in resumed.history] == pytest.approx([r["train_loss"] for r in straight.history])
    for a, b in zip(straight.model.state_dict().values(), resumed.model.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-6)


def record(run_id: str, layers: int, adjacency: int, seed: int, bleu4: float, jpe: float,
           counter: str = "predicted") -> RunRecord:
    metrics = {}
    for system, shift in (("pt", 0.0), ("sgsa", 1.0), ("ground_truth", 5.0), ("smlm", 2.0)):
        for split in ("dev", "test"):
            for lang in ("ASL-SYN", "DGS-SYN"):
                for k, base in (("bleu1", 40.0), ("bleu2", 30.0), ("bleu3", 20.0), ("bleu4", bleu4), ("rouge_l", 35.0)):
                    metrics[f"{system}/{split}/bt/slt/{lang}/{k}"] = base + shift + (1.0 if lang == "DGS-SYN" else 0.0)
            metrics[f"{system}/{split}/dtw_jpe_mean_m"] = jpe
    return RunRecord(run_id, "evaluate-sgsa", 0, "FINISHED",
                     {"sgsa.decoder_layers": str(layers), "sgsa.temporal_adjacency": str(adjacency)}, metrics, None,
                     {"seed": str(seed), "counter": counter})


def test_tables_pool_seeds_and_follow_the_paper_layouts():
    records = [record("a", 2, 0, 0, 10.0, 1.0), record("b", 2, 0, 1, 12.0, 3.0), record("c", 3, 0, 0, 8.0, 2.0),
               record("d", 2, 1, 0, 9.0, 2.0)]
    tab1 = layers_table(records).splitlines()
    header = next(line for line in tab1 if line.startswith("| L |"))
    assert header.split(" | ")[1:6] == ["dev BLEU-4", "dev BLEU-3", "dev BLEU-2", "dev BLEU-1", "dev ROUGE"]
    row = next(line for line in tab1 if line.startswith("| 2 |")).split(" | ")
    # SGSA (shift 1) BLEU-4: languages 11 / 12 -> 11.5 (seed 0), 13.5 (seed 1) -> 12.5; JPE (1 + 3) / 2 m -> 2000 mm
    assert row[1] == "12.50" and row[6] == "2000.00" and row[-1].strip(" |") == "2"
    assert any(line.startswith("| 0 (PT") for line in tab1) and any(line.startswith("| 3 |") for line in tab1)
    tab2 = adjacency_table(records)
    assert "| inf |" in tab2 and "| 1 |" in tab2 and "L = 2" in tab2
    tab3 = cross_table(records)
    for name in ("Progressive Transformers", "Skeletal Graph Self-Attention", "M3T SMLM", "Ground-truth"):
        assert name in tab3
    assert "definition 'slt'" in tab3
    # every table says how its lengths were decided
    assert all("Lengths: lengths decided by each model's own counter" in t for t in (tab2, tab3, "\n".join(tab1)))
    truth = [record(r.run_id, int(r.params["sgsa.decoder_layers"]), int(r.params["sgsa.temporal_adjacency"]),
                    int(r.tags["seed"]), 10.0, 1.0, counter="ground_truth") for r in records]
    assert "Lengths: ground-truth lengths" in cross_table(truth) and "pooled" not in cross_table(truth)
    assert "pooled" in layers_table(records + [dataclasses.replace(truth[0], run_id="z")])
    assert sweep_settings("1", [0, 1])[0] == {"sgsa.decoder_layers": 1, "sgsa.temporal_adjacency": 0,
                                              "sgsa_train.seed": 0}
    assert len(sweep_settings("2", [0])) == 5 and len(sweep_settings("1", [0, 1, 2])) == 15


def test_sgsa_flow_logs_runs_that_the_tables_read(trained, tmp_path, capsys):
    import yaml
    from prefect.testing.utilities import prefect_test_harness

    from cli.main import main as cli
    from flows.sgsa import sgsa_flow
    from m3t.experiment import fetch_runs, to_dict
    from m3t.stages import shards_version

    params, _ = trained
    params = dataclasses.replace(params, experiment=dataclasses.replace(
        params.experiment, enabled=True, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}",
        artifact_dir=str(tmp_path / "mlruns")), sgsa_evaluate=dataclasses.replace(params.sgsa_evaluate, render_clips=0))
    params_file = tmp_path / "params.yaml"
    params_file.write_text(yaml.safe_dump(to_dict(params)))
    with prefect_test_harness():
        result = sgsa_flow(params_path=str(params_file))
    assert set(result) == {"judge", "train", "evaluation"}
    runs = fetch_runs(params.experiment, stage="evaluate-sgsa")
    assert len(runs) == 1 and runs[0].tags["seed"] == str(params.sgsa_train.seed)
    assert runs[0].params["sgsa.decoder_layers"] == str(params.sgsa.decoder_layers)
    # the flow tags its runs with the shards they read, as the DVC stages do (m3t claims pairs only those)
    assert runs[0].tags["data_version"] == shards_version(params)["data_version"]
    assert {r.stage for r in fetch_runs(params.experiment)} >= {"train-backtranslation-skeleton", "train-sgsa",
                                                                  "evaluate-sgsa"}
    assert cli(["--params", str(params_file), "sgsa-table", "--table", "3"]) == 0
    table = capsys.readouterr().out
    pt_row = next(line for line in table.splitlines() if line.startswith("| Progressive Transformers"))
    cells = [c.strip() for c in pt_row.strip().strip("|").split("|")]
    assert len(cells) == 14 and "-" not in cells[1:7]  # dev BLEU-4 .. ROUGE and DTW-JPE filled from the run


def test_systems_trained_in_worker_processes_equal_one_process_on_their_threads(shards_dir, body, tmp_path):  # noqa: F811
    """``sgsa_train.workers: 2`` trains PT and SGSA in two spawned processes of one thread each (this process has
    two): the checkpoints, metrics.json and per-epoch records are those of one process that trains the systems
    one after another on one thread, up to float rounding (:mod:`float_order`)."""
    runs = {}
    for workers, threads in ((1, 1), (2, 2)):
        torch.set_num_threads(threads)  # conftest restores the count
        root = tmp_path / f"workers{workers}"
        params = tiny_params(shards_dir, root, sgsa_train={"cache_dir": str(root / "cache"), "workers": workers})
        assert worker_split(workers, 2, "cpu") == ((1, 0) if workers == 1 else (2, 1))
        records: list = []
        report = run_train(params.sgsa, params.sgsa_train, body, params.data, progress=False,
                           on_epoch=lambda system, record, epoch, out=records: out.append((system, epoch, record)))
        runs[workers] = (report, records, params.data.sgsa_dir)
    (one, one_records, one_dir), (two, two_records, two_dir) = runs[1], runs[2]
    # equal up to float rounding (tests/float_order.py)
    assert_close_numbers(one, two, "report")
    assert len(one_records) == 2 * params.sgsa_train.epochs
    assert_close_numbers(one_records, two_records, "records")  # replayed in system order
    assert_close_json(one_dir / "metrics.json", two_dir / "metrics.json")
    for name in ("pt.pt", "sgsa.pt"):
        assert_close_weights(one_dir, two_dir, name)


def test_the_length_penalty_is_symmetric_in_too_long_and_too_short():
    from m3t.sgsa.evaluate import length_penalty

    assert length_penalty(10, 10) == 1.0
    assert length_penalty(20, 10) == length_penalty(5, 10) == 2.0  # twice too long, twice too short
    assert length_penalty(1, 40) == 40.0  # one frame for forty: the raw DTW cost alone would not see it
    assert length_penalty(0, 10) == float("inf")


def test_the_smlms_generation_is_scored_and_judged_beside_the_trained_systems(trained, body, shards_dir, tmp_path,
                                                                                capsys):
    """When generate-smlm wrote the split, its decoded motion is posed into the same skeleton and scored and
    judged like PT and SGSA (the ``smlm`` rows). The "generation" here is the test clips' own tokens under tiny
    untrained tokenizers (what generate-smlm writes, without an SMLM); one clip has no tokens (an empty
    generation: the rest pose)."""
    import shutil

    from m3t.shards.tokens import TokenClip, write_token_shard
    from m3t.tokenizers.checkpoint import save_tokenizer
    from m3t.tokenizers.config import TokenizerConfig
    from m3t.tokenizers.data import GROUPS, clip_sequences, normalisation
    from m3t.tokenizers.tokenize import load_tokenizers, tokenize_clip
    from m3t.tokenizers.vae import MotionTokenizer

    params, _ = trained
    shutil.copytree(params.data.models_dir, tmp_path / "models")  # the module's trained systems and judge
    data = dataclasses.replace(params.data, models_dir=str(tmp_path / "models"), generated_dir=str(tmp_path / "gen"),
                               metrics_dir=str(tmp_path / "metrics"))
    torch.manual_seed(0)
    train = read_split([shards_dir], "train")
    for group in GROUPS:
        seqs = [s for f in train for s in clip_sequences(f.params, group)]
        model = MotionTokenizer(TokenizerConfig(width=16, depth=1).vae_config(group, seqs[0].shape[1]))
        model.set_normalisation(*normalisation(seqs))
        save_tokenizer(data.tokenizers_dir / f"{group}.pt", model.eval(), group, 1, 1, "v", {})
    tokenizers, info = load_tokenizers(data.tokenizers_dir)
    test = read_split([shards_dir], "test")
    generated = [tokenize_clip(tokenizers, f) for f in test]
    empty = generated[0]
    generated[0] = TokenClip(empty.clip, 0, {s: np.zeros(0, np.int64) for s in empty.tokens})
    data.generated.mkdir(parents=True)
    write_token_shard(data.generated / "generated.parquet", generated, info)

    cfg = dataclasses.replace(params.sgsa_evaluate, splits=("dev", "test"), render_clips=1)
    summary = run_evaluate(params.sgsa, cfg, body, data, params.backtranslation, progress=True)
    assert "dtw" in capsys.readouterr().err  # the DTW progress bar, when asked for
    assert not any(k.startswith("smlm/dev/") for k in summary)  # generate-smlm wrote the test split only
    assert summary["smlm/test/clips"] == len(test) == summary["test/clips"] and summary["dev/clips"] > 0
    for key in ("dtw_jpe_mean_m", "dtw_jpe_body_m", "dtw_jpe_hand_m"):
        assert np.isfinite(summary[f"smlm/test/{key}"]) and summary[f"smlm/test/{key}"] > 0
    assert summary["smlm/test/dtw_jpe_mean_m"] == pytest.approx(
        0.5 * (summary["smlm/test/dtw_jpe_body_m"] + summary["smlm/test/dtw_jpe_hand_m"]))
    assert "smlm/test/bt/slt_bleu4" in summary
    out = data.metrics("sgsa")
    rows = [line.split(",") for line in (out / "per_clip.csv").read_text().splitlines()[1:]]
    assert sorted(r[2] for r in rows if r[0] == "smlm") == sorted(f.clip.id for f in test)
    judged = [line.split(",") for line in (out / "backtranslation.csv").read_text().splitlines()[1:]]
    sentences = sorted(r[2] for r in judged if r[0] == "ground_truth" and r[1] == "test")  # the split's sentences
    assert sorted(r[2] for r in judged if r[0] == "smlm") == sentences and sentences
    # the video of the shown clip has the SMLM's skeleton beside the systems'
    assert len(list((out / "videos").glob("*.mp4"))) == 1


def test_evaluation_without_checkpoints_names_the_stage_to_run(tmp_path):
    from m3t.sgsa.pipeline import load_systems
    from m3t.shards.folders import DataConfig

    data = DataConfig(models_dir=str(tmp_path / "models"))
    with pytest.raises(FileNotFoundError, match=r"no SGSA / PT checkpoint in .*sgsa; run `dvc repro train-sgsa` "
                                                r"\(python -m m3t.stages.train_sgsa\) first$"):
        load_systems(data)
    data.sgsa_dir.mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="no SGSA / PT checkpoint"):
        load_systems(data)  # an empty folder too
