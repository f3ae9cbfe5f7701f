"""The edge cases of shard validation (:mod:`m3t.shards.schema`, :mod:`m3t.shards.tokens`,
:mod:`m3t.shards.skeletons`): one-frame clips, width-one and empty streams, token shards with unparsable metadata or
of another kind named, and the skeleton view of a fit. Written to pin behaviours that mutation testing found
unchecked.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from m3t.body.protocol import Modality, ModalityLayout
from m3t.corpora.clip import Clip
from m3t.shards.io import validate_clip, write_shard
from m3t.shards.schema import FittedClip, ShardFormatError, arrow_schema
from m3t.shards.tokens import TokenClip, TokenInfo, read_token_shard, write_token_shard

# ----------------------------------------------------------------------------------------- shards
LAYOUT = ModalityLayout(
    modalities=(Modality("body", "rotation6d", ("pelvis",)), Modality("face", "scalar", ("jaw_open",))),
    identity_labels=("height", "weight"),
)


def _fitted(frames: int, layout: ModalityLayout = LAYOUT, cid: str = "csl-0007") -> FittedClip:
    clip = Clip(id=cid, corpus="toy", split="train", language="CSL", signer="s1", text="你好", gloss="你好",
                media=f"video/{cid}.mp4", fps=25.0)
    params = {m.name: np.zeros((frames, m.dim), np.float32) for m in layout.modalities}
    return FittedClip(clip, "sha256:0", params, np.zeros(layout.identity_dim, np.float32), {}, {}, "anny")


def test_a_one_frame_clip_is_valid_and_a_clip_without_frames_is_refused(tmp_path):
    validate_clip(_fitted(1), LAYOUT)
    path = write_shard(tmp_path / "one.parquet", [_fitted(1)], LAYOUT)
    assert pq.read_metadata(path).num_rows == 1
    with pytest.raises(ValueError, match=r"clip 'csl-0007': has no frames"):
        validate_clip(_fitted(0), LAYOUT)
    with pytest.raises(ValueError, match=r"clip 'csl-0007', modality 'face': 2 frames, other modalities have 3"):
        validate_clip(FittedClip(**{**_fitted(3).__dict__, "params": {"body": np.zeros((3, 6), np.float32),
                                                                       "face": np.zeros((2, 1), np.float32)}}), LAYOUT)


def test_schema_accepts_width_one_streams_and_refuses_empty_ones():
    one = ModalityLayout((Modality("face", "scalar", ("jaw_open",)),), ("height",))
    schema = arrow_schema(one)
    assert schema.field("face").type.value_type.list_size == 1 and schema.field("identity").type.list_size == 1
    empty = ModalityLayout((Modality("face", "scalar", ()), Modality("body", "rotation6d", ("pelvis",))), ("h",))
    with pytest.raises(ValueError, match=r"streams \['face'\] have dim 0"):
        arrow_schema(empty)
    with pytest.raises(ValueError, match=r"streams \['identity'\] have dim 0"):
        arrow_schema(ModalityLayout((Modality("face", "scalar", ("jaw_open",)),), ()))


def test_token_shard_with_unparsable_metadata_names_the_file_and_key(tmp_path):
    info = TokenInfo({"body": 8}, 4, {"body": "sha256:ab"})
    clip = TokenClip(_fitted(1).clip, 5, {"body": np.array([1, 7])})
    path = write_token_shard(tmp_path / "tokens.parquet", [clip], info)
    assert read_token_shard(path).clips[0].tokens["body"].tolist() == [1, 7]
    table = pq.read_table(path)
    for bad in (b"{not json", b'{"streams": {"body": 8}}', b'{"streams": [], "downsample": 4, "tokenizers": {}}'):
        meta = dict(table.schema.metadata) | {b"m3t.tokens": bad}
        pq.write_table(table.replace_schema_metadata(meta), tmp_path / "bad.parquet")
        with pytest.raises(ShardFormatError) as err:
            read_token_shard(tmp_path / "bad.parquet")
        message = str(err.value)
        assert str(tmp_path / "bad.parquet") in message and "m3t.tokens metadata" in message
        assert "rerun the tokenize stage" in message


@pytest.mark.parametrize("kind", ["body", "holistic"])
def test_skeleton_clip_poses_the_fit_into_the_graph_and_normalises_it(body, kind):
    from m3t.body.skeleton import graph_for
    from m3t.body.skeleton_points import denormalise
    from m3t.shards.skeletons import SKELETON_STREAM, skeleton_clip

    graph = graph_for(kind)
    params = {k: v.numpy() for k, v in body.rest_params(2).items()}
    fitted = FittedClip(_fitted(2).clip, "sha256:1", params, body.default_identity().numpy(), {}, {}, body.name)
    sk = skeleton_clip(body, fitted, graph)
    assert sk.clip_id == "csl-0007" and sk.points.shape == (2, len(graph.joints), 3)
    assert sk.coords.shape == (2, graph.width) and sk.coords.dtype == np.float32
    left, right = graph.index("body:left_shoulder"), graph.index("body:right_shoulder")
    width = np.linalg.norm(sk.points[:, left] - sk.points[:, right], axis=-1).mean()
    assert 0.2 < sk.scale < 0.5 and sk.scale == pytest.approx(width)  # metres: an adult's shoulder width
    np.testing.assert_allclose(sk.coords[:, :3], 0, atol=1e-6)  # neck-centred
    np.testing.assert_allclose(denormalise(sk.coords, graph, sk.scale), sk.points - sk.points[:, :1], atol=1e-5)
    as_fitted = sk.as_fitted()
    assert set(as_fitted.params) == {SKELETON_STREAM} and as_fitted.clip == fitted.clip
    broken = {k: v.copy() for k, v in params.items()}
    broken["body"][:] = np.nan
    with pytest.raises(ValueError, match=r"clip 'csl-0007': skeleton .*degenerate clip"):
        skeleton_clip(body, FittedClip(fitted.clip, "k", broken, fitted.identity, {}, {}, body.name), graph)


def test_token_shard_reader_refuses_other_files_naming_the_file_and_the_fix(tmp_path):
    info = TokenInfo({"body": 8, "face": 4}, 2, {"body": "sha256:ab", "face": "sha256:cd"})
    clips = [TokenClip(_fitted(1, cid=f"c{i}").clip, 3, {"body": np.array([i, 7]), "face": np.array([3, 0])})
             for i in range(2)]
    path = write_token_shard(tmp_path / "tokens.parquet", clips, info)
    shard = read_token_shard(path)
    assert shard.path == path and shard.info == info and [c.clip.id for c in shard.clips] == ["c0", "c1"]
    assert shard.clips[1].num_frames == 3 and shard.clips[1].tokens["face"].dtype == np.int64
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    cases = {
        "no_meta": (table.replace_schema_metadata({}), r"not an m3t token shard of version 1 \(found none\)"),
        "version_2": (table.replace_schema_metadata(meta | {b"m3t.token_schema_version": b"2"}), r"\(found 2\)"),
        "no_info": (table.replace_schema_metadata({b"m3t.token_schema_version": b"1"}), r"\(found 1\)"),
        "no_face": (table.drop(["face"]), r"column 'face' is missing"),
        "bad_row": (table.set_column(table.schema.get_field_index("num_frames"), "num_frames",
                                     pa.array([3, 9], pa.int32())).replace_schema_metadata(meta),
                    r"row 1 \(0-based\): clip 'c1', stream 'body': 2 tokens, expected ceil\(9 / 2\) = 5"),
    }
    for name, (bad, fragment) in cases.items():
        pq.write_table(bad, tmp_path / f"{name}.parquet")
        with pytest.raises(ShardFormatError, match=fragment) as err:
            read_token_shard(tmp_path / f"{name}.parquet")
        assert str(tmp_path / f"{name}.parquet") in str(err.value) and "rerun the tokenize stage" in str(err.value)
