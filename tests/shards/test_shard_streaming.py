"""Shards in bounded memory: row groups of about ``ROW_GROUP_FRAMES`` frames written by :class:`ShardWriter` and read
one at a time by :func:`iter_shard` / :func:`iter_split`, equal to the whole-shard write and read; their refusals
(repeated ids across batches, groups or corpora, a damaged frame in a later group) and the tokenisation stage
streaming over them. The budget is made a few frames small so that toy clips span several groups."""
from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from builders import tiny_tokenizers
from test_shards import LAYOUT, clips, make_clip  # noqa: F401 - clips: the six toy clips of 5 .. 40 frames

import m3t.shards.io as shard_io
from m3t.shards import (
    FittedClip,
    ShardFormatError,
    ShardWriter,
    iter_shard,
    read_shard,
    write_shard,
)
from m3t.shards.io import iter_split, read_split
from m3t.tokenizers.tokenize import tokenize_corpus
from tests.tokenizers.test_tokenize import tiny_info, write_tiny_shards

SMALL = 20
"""A row-group budget that splits the toy clips (5, 12, 19, 26, 33, 40 frames) into [5, 12], [19], [26], ..."""


def assert_same_clips(got: list[FittedClip], want: list[FittedClip]) -> None:
    """Every field equal, arrays exactly (one process, no float round trip), NaN metrics as NaN."""
    assert [c.clip.id for c in got] == [c.clip.id for c in want]
    for a, b in zip(got, want):
        assert a.clip == b.clip and a.key == b.key and a.body_model == b.body_model and a.camera == b.camera
        assert a.metrics.keys() == b.metrics.keys()
        assert all(a.metrics[k] == v or (math.isnan(a.metrics[k]) and math.isnan(v)) for k, v in b.metrics.items())
        np.testing.assert_array_equal(a.identity, b.identity)
        assert a.params.keys() == b.params.keys()
        for name in b.params:
            assert a.params[name].dtype == np.float32
            np.testing.assert_array_equal(a.params[name], b.params[name])


def test_a_shard_of_several_row_groups_reads_as_its_groups_and_as_one_group(tmp_path, clips, monkeypatch):  # noqa: F811
    single = write_shard(tmp_path / "single.parquet", clips, LAYOUT)
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    path = write_shard(tmp_path / "grouped.parquet", clips, LAYOUT)
    assert pq.ParquetFile(single).num_row_groups == 1
    assert pq.ParquetFile(path).num_row_groups == 5
    groups = list(iter_shard(path))
    # whole clips; a group is closed once it reaches the budget, a clip longer than it is a group of its own
    assert [g.lengths.tolist() for g in groups] == [[5, 12], [19], [26], [33], [40]]
    assert all(g.layout == LAYOUT and g.path == path for g in groups)
    shard = read_shard(path)
    assert_same_clips(list(shard.clips), [c for g in groups for c in g.clips])
    np.testing.assert_array_equal(shard.lengths, np.concatenate([g.lengths for g in groups]))
    assert shard.lengths.dtype == np.int64
    assert_same_clips(list(shard.clips), list(read_shard(single).clips))
    assert_same_clips(list(shard.clips), clips)
    faces = list(iter_shard(path, modalities=["face"]))
    assert all(set(c.params) == {"face"} for g in faces for c in g)
    assert [c.clip.id for g in faces for c in g] == shard.ids


@pytest.mark.parametrize("budget", [SMALL, shard_io.ROW_GROUP_FRAMES])
def test_shard_writer_over_batches_writes_the_bytes_of_write_shard(tmp_path, clips, monkeypatch, budget):  # noqa: F811
    """Row groups follow the clips, not the batches: any split into ``write`` calls gives the same file."""
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", budget)
    whole = write_shard(tmp_path / "whole.parquet", clips, LAYOUT)
    with ShardWriter(tmp_path / "batched.parquet", LAYOUT) as writer:
        for batch in (clips[:1], [], clips[1:4], clips[4:]):
            writer.write(batch)
        assert not (tmp_path / "batched.parquet").exists()  # appears when the block ends
    assert writer.clips_written == 6 and writer.frames_written == sum(c.num_frames for c in clips)
    assert (tmp_path / "batched.parquet").read_bytes() == whole.read_bytes()
    with ShardWriter(tmp_path / "empty.parquet", LAYOUT):
        pass
    assert (tmp_path / "empty.parquet").read_bytes() == write_shard(tmp_path / "none.parquet", [], LAYOUT).read_bytes()
    assert len(read_shard(tmp_path / "empty.parquet")) == 0


def test_an_id_repeated_in_a_later_batch_is_refused_and_nothing_written(tmp_path, clips, monkeypatch):  # noqa: F811
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    again = make_clip(1, 3, np.random.default_rng(5))
    with pytest.raises(ValueError) as err, ShardWriter(tmp_path / "a.parquet", LAYOUT) as writer:
        writer.write(clips[:3])
        writer.write([clips[4], again])
    assert str(err.value) == "clip 'clip-0001' appears twice; clip ids must be unique within a shard"
    assert writer.clips_written == 3  # none of the refused batch was taken, not even its first clip
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("existing", [True, False])
def test_an_error_in_the_block_leaves_no_file_and_the_older_shard(tmp_path, clips, monkeypatch, existing):  # noqa: F811
    dest = tmp_path / "a.parquet"
    if existing:
        write_shard(dest, clips[:2], LAYOUT)
    before = dest.read_bytes() if existing else None
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    with pytest.raises(RuntimeError, match="fit crashed"), ShardWriter(dest, LAYOUT) as writer:
        writer.write(clips)
        # the groups went to the temporary file as they filled (only an unfinished group waits in memory)
        assert [p.stat().st_size > 1000 for p in tmp_path.glob(".a.parquet.*.tmp")] == [True]
        raise RuntimeError("fit crashed")
    assert sorted(p.name for p in tmp_path.iterdir()) == (["a.parquet"] if existing else [])
    if existing:
        assert dest.read_bytes() == before


def _grouped(table: pa.Table, out, rows_per_group: int):
    """``table`` (a shard's, edited) written to ``out`` in row groups of ``rows_per_group`` rows."""
    pq.write_table(table, out, row_group_size=rows_per_group)
    assert pq.ParquetFile(out).num_row_groups > 1
    return out


@pytest.mark.parametrize("damage", [math.nan, math.inf])
def test_a_damaged_frame_in_a_later_group_names_its_row_in_the_shard(tmp_path, clips, damage):  # noqa: F811
    table = pq.read_table(write_shard(tmp_path / "a.parquet", clips, LAYOUT))
    column = table.column("face").to_pylist()
    column[4][7][2] = damage
    field = table.schema.field("face")
    damaged = table.set_column(table.schema.get_field_index("face"), field, pa.array(column, type=field.type))
    out = _grouped(damaged, tmp_path / "damaged.parquet", rows_per_group=2)  # row 4 is the third group's first
    groups = iter_shard(out)
    assert [len(next(groups)), len(next(groups))] == [2, 2]  # the groups before are read
    message = (f"{out}: row 4 (0-based), column 'face' holds NaN or inf; the shard is damaged (re-run the stage "
               "that wrote it)")
    with pytest.raises(ShardFormatError) as err:
        next(groups)
    assert str(err.value) == message
    with pytest.raises(ShardFormatError) as err:
        read_shard(out)
    assert str(err.value) == message


def test_a_clip_id_repeated_in_a_later_row_group_is_refused(tmp_path, clips):  # noqa: F811
    table = pq.read_table(write_shard(tmp_path / "a.parquet", clips, LAYOUT))
    ids = table.column("id").to_pylist()
    ids[5] = ids[0]
    edited = table.set_column(table.schema.get_field_index("id"), table.schema.field("id"), pa.array(ids, pa.string()))
    out = _grouped(edited, tmp_path / "twice.parquet", rows_per_group=2)  # row 5 is in the third group, row 0 the first
    for read in (lambda: list(iter_shard(out)), lambda: read_shard(out)):
        with pytest.raises(ShardFormatError) as err:
            read()
        assert str(err.value) == (f"{out}: clip ids ['clip-0000'] appear twice; the shard is damaged (re-run the "
                                  "stage that wrote it)")


def test_iter_split_streams_corpora_in_order_and_refuses_an_id_in_two(tmp_path, clips, monkeypatch):  # noqa: F811
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    alpha, beta, gamma = (tmp_path / name for name in ("alpha", "beta", "gamma"))
    for folder, part in ((alpha, clips[:3]), (beta, clips[3:]), (gamma, clips[2:4])):
        folder.mkdir()
        write_shard(folder / "train.parquet", part, LAYOUT)
    assert_same_clips(list(iter_split([alpha, beta], "train")), clips)
    assert_same_clips(read_split([alpha, beta], "train"), clips)
    assert [c.clip.id for c in iter_split(alpha, "train", modalities=[])] == [c.clip.id for c in clips[:3]]
    streamed = iter_split([alpha, gamma], "train")
    assert [next(streamed).clip.id for _ in range(3)] == ["clip-0000", "clip-0001", "clip-0002"]
    with pytest.raises(ValueError) as err:
        next(streamed)
    assert str(err.value) == (f"clip id 'clip-0002' is in both {alpha / 'train.parquet'} and "
                              f"{gamma / 'train.parquet'}; clip ids must be unique across data.train_corpora")
    # a missing shard is named at the call, before a clip of the corpora before it is read
    with pytest.raises(FileNotFoundError, match=r"shard .*missing/train\.parquet not found; run the fit-corpus stage"):
        iter_split([alpha, tmp_path / "missing"], "train")


def test_tokenize_over_several_row_groups_writes_the_bytes_of_the_one_group_shards(tmp_path, monkeypatch):
    models = tiny_tokenizers()
    info = tiny_info(models)
    write_tiny_shards(tmp_path / "single")
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", 8)
    write_tiny_shards(tmp_path / "grouped")
    assert pq.ParquetFile(tmp_path / "grouped" / "train.parquet").num_row_groups == 3  # 9 | 2 | 16 frames
    assert pq.ParquetFile(tmp_path / "single" / "train.parquet").num_row_groups == 1
    summaries = [tokenize_corpus(models, info, tmp_path / f, tmp_path / "tokens" / f) for f in ("single", "grouped")]
    assert summaries[0] == summaries[1] and summaries[0]["rejected"] == 1
    for name in ("train.parquet", "dev.parquet", "test.parquet", "rejected.jsonl", "summary.json"):
        assert (tmp_path / "tokens" / "grouped" / name).read_bytes() == (tmp_path / "tokens" / "single" / name).read_bytes()


# ---------------------------------------------------------------- a split's references left in their shards
def test_split_references_hold_metadata_and_read_parameters_from_their_row_group(tmp_path, clips,  # noqa: F811
                                                                                monkeypatch):
    from m3t.shards.references import SplitReferences

    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    for corpus, part in (("one", clips[:4]), ("two", clips[4:])):
        (tmp_path / corpus).mkdir()
        write_shard(tmp_path / corpus / "test.parquet", part, LAYOUT)
    folders = [tmp_path / "one", tmp_path / "two"]
    refs = SplitReferences(folders, "test")
    assert list(refs) == [c.clip.id for c in clips] and len(refs) == 6
    assert refs._group is None, "building the references reads no parameter column"
    want = read_split(folders, "test")
    for got in (refs[c.clip.id] for c in want):
        assert got.num_frames == len(next(iter(got.params.values())))
    # every field, parameters included, equal to reading the split; one row group held at a time
    assert_same_clips([refs[c.clip.id] for c in want], want)
    reads = []
    monkeypatch.setattr("m3t.shards.references.read_row_group",
                        lambda *where: reads.append(where) or shard_io.read_row_group(*where))
    for cid in ("clip-0000", "clip-0001", "clip-0002", "clip-0000", "clip-0005"):
        refs[cid].params  # noqa: B018 - the read is the point
    # clip-0000 and -0001 share the first group of "one"; clip-0002 is the next; -0005 the second group of "two"
    assert reads == [(folders[0] / "test.parquet", 0), (folders[0] / "test.parquet", 1),
                     (folders[0] / "test.parquet", 0), (folders[1] / "test.parquet", 1)]
    assert len(refs._group[1]) == 1


def test_split_references_refuse_an_id_in_two_corpora_and_name_a_missing_shard(tmp_path, clips):  # noqa: F811
    from m3t.shards.references import SplitReferences

    for corpus in ("one", "two"):
        (tmp_path / corpus).mkdir()
        write_shard(tmp_path / corpus / "test.parquet", clips[:2], LAYOUT)
    with pytest.raises(ValueError, match=r"clip id 'clip-0000' is in both .*one.*two"):
        SplitReferences([tmp_path / "one", tmp_path / "two"], "test")
    with pytest.raises(FileNotFoundError, match=r"fit-corpus"):
        SplitReferences([tmp_path / "one", tmp_path / "three"], "test")


def test_a_row_group_read_alone_is_checked_and_names_its_row_in_the_shard(tmp_path, clips, monkeypatch):  # noqa: F811
    monkeypatch.setattr(shard_io, "ROW_GROUP_FRAMES", SMALL)
    path = write_shard(tmp_path / "s.parquet", clips, LAYOUT)
    assert_same_clips(list(shard_io.read_row_group(path, 2).clips), [clips[3]])
    with pytest.raises(IndexError, match=r"no row group 5; the shard has 5"):
        shard_io.read_row_group(path, 5)
    table = pq.read_table(path)
    column = table.column("face").to_pylist()
    column[4][1][0] = math.nan
    field = table.schema.field("face")
    damaged = table.set_column(table.schema.get_field_index("face"), field, pa.array(column, type=field.type))
    out = _grouped(damaged, tmp_path / "damaged.parquet", rows_per_group=2)  # row 4 is the third group's first
    assert len(shard_io.read_row_group(out, 1)) == 2  # the groups around it read
    with pytest.raises(ShardFormatError, match=r"damaged.parquet: row 4 \(0-based\), column 'face' holds NaN"):
        shard_io.read_row_group(out, 2)


def test_a_row_group_decoded_a_few_rows_at_a_time_reads_as_one_and_keeps_its_checks(tmp_path, clips,  # noqa: F811
                                                                                   monkeypatch):
    """Groups are decoded ``READ_BATCH_ROWS`` clips at a time (Arrow's temporaries for a whole group are several
    times its values): iter_split streams such batches, iter_shard and read_row_group join them into the group.
    The checks still span the group: an id repeated in a later batch, a damaged frame's row in the shard."""
    path = write_shard(tmp_path / "one_group.parquet", clips, LAYOUT)  # six clips, one row group
    assert pq.ParquetFile(path).num_row_groups == 1
    monkeypatch.setattr(shard_io, "READ_BATCH_ROWS", 4)
    decoded: list[int] = []
    contents = shard_io._contents
    monkeypatch.setattr(shard_io, "_contents", lambda table, *rest: decoded.append(table.num_rows) or
                        contents(table, *rest))
    groups = list(iter_shard(path))
    assert len(groups) == 1 and groups[0].lengths.tolist() == [c.num_frames for c in clips]
    assert decoded == [4, 2]  # the group took two decodes, not one
    assert_same_clips(list(groups[0].clips), clips)
    assert_same_clips(list(shard_io.read_row_group(path, 0).clips), clips)
    split = tmp_path / "corpus"
    split.mkdir()
    path.rename(split / "train.parquet")
    assert_same_clips(list(iter_split(split, "train")), clips)
    path = split / "train.parquet"
    table = pq.read_table(path)
    ids = table.column("id").to_pylist()
    ids[5] = ids[1]  # the second batch repeats an id of the first
    twice = table.set_column(table.schema.get_field_index("id"), table.schema.field("id"), pa.array(ids, pa.string()))
    pq.write_table(twice, tmp_path / "twice.parquet")
    for read in (lambda p: list(iter_shard(p)), read_shard, lambda p: shard_io.read_row_group(p, 0)):
        with pytest.raises(ShardFormatError, match=r"clip ids \['clip-0001'\] appear twice"):
            read(tmp_path / "twice.parquet")
    column = table.column("body").to_pylist()
    column[5][3][0] = math.inf
    field = table.schema.field("body")
    pq.write_table(table.set_column(table.schema.get_field_index("body"), field, pa.array(column, type=field.type)),
                   tmp_path / "damaged.parquet")
    with pytest.raises(ShardFormatError, match=r"damaged.parquet: row 5 \(0-based\), column 'body' holds NaN or inf"):
        shard_io.read_row_group(tmp_path / "damaged.parquet", 0)
