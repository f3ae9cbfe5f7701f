"""The ``.pose`` reader (:mod:`m3t.corpora.posefile`) and the fingerspelling corpus built on it
(:mod:`m3t.corpora.fingerspelling`): 2D and partly masked bodies, version 0.1 files, index rows and their defaults,
letter tables, reproducible splits and spelled words, resampling of letter clips. Written to pin behaviours that
mutation testing found unchecked.
"""
from __future__ import annotations

import csv
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from m3t.corpora.clip import Clip
from m3t.corpora.fingerspelling import (
    FingerspellingConfig,
    FingerspellingCorpus,
    concatenate,
    lexicon_root,
    resample,
    spelled_paths,
)
from m3t.corpora.listing import Collector, CorpusError, Quarantined
from m3t.corpora.posefile import (
    PoseData,
    PoseFileConfig,
    PoseFileCorpus,
    pose_data,
    read_pose,
    read_pose_info,
)
from m3t.corpora.splits import hash_split


@pytest.fixture(scope="module")
def ase_rows() -> list[dict]:
    """Two ASL letter rows of the lexicon's ``data.csv`` (the spoken-to-signed wheel's own table)."""
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh) if r["signed_language"] == "ase"][:2]


# ----------------------------------------------------------------------------------------- .pose bodies
def _openpose_hand_pose(frames: int, masked: tuple[int, int] | None):
    """A 2D ``Pose`` with one OpenPose hand component (21 points, point format XYC), the layout pose-format
    itself ships for OpenPose output (``pose_format.utils.openpose.OpenPose_Hand_Component``). Confidence 0.9
    everywhere; ``masked``: (frame, point) whose coordinates are masked."""
    from pose_format import Pose
    from pose_format.numpy.pose_body import NumPyPoseBody
    from pose_format.pose_header import PoseHeader, PoseHeaderDimensions
    from pose_format.utils.openpose import OpenPose_Hand_Component

    header = PoseHeader(0.2, PoseHeaderDimensions(640, 480), [OpenPose_Hand_Component("hand_right_keypoints_2d")])
    rng = np.random.default_rng(0)
    data = np.ma.masked_array(rng.uniform(0, 400, (frames, 1, 21, 2)).astype(np.float32),
                              mask=np.zeros((frames, 1, 21, 2), bool))
    if masked is not None:
        data.mask[masked[0], 0, masked[1]] = True
    confidence = np.full((frames, 1, 21), 0.9, np.float32)
    return Pose(header, NumPyPoseBody(25.0, data, confidence))


def test_two_dimensional_pose_is_read_with_zero_depth():
    pose = _openpose_hand_pose(3, None)
    data = pose_data(pose, "hand.pose")
    assert data.points.shape == (3, 21, 3) and data.points.dtype == np.float32 and data.dims == 2
    np.testing.assert_array_equal(data.points[..., :2], np.ma.getdata(pose.body.data)[:, 0])
    assert np.all(data.points[..., 2] == 0)
    assert data.components == (("hand_right_keypoints_2d", 21),) and (data.width, data.height) == (640, 480)
    assert data.fps == 25.0 and data.point_names[0][0] == "BASE"


def test_masked_pose_points_get_zero_confidence():
    data = pose_data(_openpose_hand_pose(4, masked=(2, 5)), "hand.pose")
    assert data.confidence.shape == (4, 21) and data.confidence.dtype == np.float32
    assert data.confidence[2, 5] == 0.0
    expected = np.full((4, 21), 0.9, np.float32)
    expected[2, 5] = 0.0
    np.testing.assert_array_equal(data.confidence, expected)


def test_pose_body_without_frames_or_person_is_refused_naming_the_file():
    with pytest.raises(CorpusError, match="hand.pose: no frames"):
        pose_data(_openpose_hand_pose(0, None), "hand.pose")
    with pytest.raises(CorpusError, match=r"hand.pose has 1 person\(s\); person=1"):
        pose_data(_openpose_hand_pose(2, None), "hand.pose", person=1)


# ----------------------------------------------------------------------------------------- .pose collections
def test_pose_index_rows_with_empty_language_and_signer_default_to_unknown(tmp_path, ase_rows):
    (tmp_path / "p").mkdir()
    for i, row in enumerate(ase_rows):
        shutil.copyfile(lexicon_root() / row["path"], tmp_path / "p" / f"{i}.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer\n"
                                        "a,p/0.pose,train,A,,\nb,p/1.pose,test,B,ase,s1\n", encoding="utf-8")
    clips = {c.id: c for c in PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing().clips}
    assert (clips["a"].language, clips["a"].signer, clips["a"].gloss) == ("unknown", "unknown", "")
    assert (clips["b"].language, clips["b"].signer, clips["b"].text) == ("ase", "s1", "B")


def test_pose_clip_extra_records_frames_people_and_components(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig()).listing().clips
    info = read_pose_info(tmp_path / "a.pose")
    assert info.frames > 0 and info.people == 1
    assert dict(clip.extra) == {"media_kind": "pose", "frames": str(info.frames), "people": "1",
                                "components": ",".join(f"{n}:{k}" for n, k in info.components)}
    assert clip.fps == info.fps and clip.media == "a.pose" and clip.id == "a"


def test_unreadable_letter_file_is_quarantined_naming_the_clip_and_the_relative_path(tmp_path, ase_rows):
    """A fingerspelling table in the lexicon's ``data.csv`` layout (spoken-to-signed's
    ``assets/fingerspelling_lexicon/data.csv``, e.g. ``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,
    0,2720,A,A,0``) whose second letter file is cut in half."""
    (tmp_path / "ase").mkdir()
    good, cut = (Path(r["path"]) for r in ase_rows)
    shutil.copyfile(lexicon_root() / good, tmp_path / good)
    data = (lexicon_root() / cut).read_bytes()
    (tmp_path / cut).write_bytes(data[: len(data) // 2])
    with open(tmp_path / "data.csv", "w", encoding="utf-8", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(ase_rows[0]))
        writer.writeheader()
        writer.writerows(ase_rows)
    listing = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=0)).listing()
    assert [c.id for c in listing.clips] == [f"ase-{good.stem}"]
    (q,) = listing.quarantined
    assert (q.file, q.row, q.clip_id) == ("data.csv", 3, f"ase-{cut.stem}")
    assert q.reason.startswith(f"{cut.as_posix()}: truncated") and str(tmp_path) not in q.reason


# ----------------------------------------------------------------------------------------- fingerspelling lexicon
def _letter_table(root: Path, rows: list[dict], extra_lines: tuple[str, ...] = ()) -> Path:
    """A copy of ``rows`` of the lexicon's ``data.csv`` (spoken-to-signed's ``assets/fingerspelling_lexicon/
    data.csv``, e.g. ``ase/fs-stse28e9ac023b0e29ca0a3acc12dc46540.pose,en,ase,0,2720,A,A,0``) with their real
    ``.pose`` files, plus ``extra_lines`` appended verbatim."""
    for r in rows:
        (root / r["path"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(lexicon_root() / r["path"], root / r["path"])
    with open(root / "data.csv", "w", encoding="utf-8", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        fh.writelines(line + "\n" for line in extra_lines)
    return root / "data.csv"


@pytest.fixture(scope="module")
def ase_letters() -> list[dict]:
    """The first four ASL letter rows (A, B, C, D) of the lexicon's ``data.csv``."""
    with open(lexicon_root() / "data.csv", encoding="utf-8") as fh:
        return [r for r in csv.DictReader(fh) if r["signed_language"] == "ase"][:4]


def test_letter_table_quarantines_paths_leaving_the_lexicon_and_repeated_letters(tmp_path, ase_letters):
    table = _letter_table(tmp_path, ase_letters[:2], (
        "../ase/escape.pose,en,ase,0,100,E,E,0",
        "ase/../../escape.pose,en,ase,0,100,F,F,0",
        "/abs/ase/g.pose,en,ase,0,100,G,G,0",
        "ase/again.pose,en,ase,0,100,a,a,0",
        "ase/h.pose,en,ase,0,100,,,0",
        "ase/i.pose,en,ase,0,100,I,I,0,extra"))
    out = Collector(tmp_path)
    letters = FingerspellingCorpus(tmp_path).table(out)
    assert [(x.letter, x.language, x.label, x.row, x.path) for x in letters] == [
        ("A", "ase", 0, 2, ase_letters[0]["path"]), ("B", "ase", 1, 3, ase_letters[1]["path"])]
    assert (letters[0].spoken_language, letters[0].start_ms, letters[0].end_ms) == ("en", "0", ase_letters[0]["end"])
    malformed = "malformed row: empty signed_language, words or path, or extra columns"
    assert out.listing().quarantined == (
        Quarantined("data.csv", 4, None, "path ../ase/escape.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 5, None, "path ase/../../escape.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 6, None, "path /abs/ase/g.pose must be relative to the lexicon folder"),
        Quarantined("data.csv", 7, None, "letter 'a' listed twice for ase"),
        Quarantined("data.csv", 8, None, malformed), Quarantined("data.csv", 9, None, malformed))
    assert [x.letter for x in FingerspellingCorpus(tmp_path).table()] == ["A", "B"]  # without a collector: skipped
    table.unlink()
    with pytest.raises(CorpusError) as err:
        FingerspellingCorpus(tmp_path).table()
    assert str(err.value) == f"{table} not found. Reinstall spoken-to-signed."


def test_fingerspelling_splits_and_spelled_words_are_reproducible(tmp_path, ase_letters):
    """Splits and the drawn words are part of the data version: a re-listing must give the same ones (pinned),
    and every clip, letter or word, takes the corpus's hash split of its id."""
    _letter_table(tmp_path, ase_letters)
    fractions = (0.4, 0.3, 0.3)
    cfg = FingerspellingConfig(words_per_language=3, max_letters=3, split_fractions=fractions, seed=1)
    clips = FingerspellingCorpus(tmp_path, cfg).listing().clips
    assert [(c.text, c.split) for c in clips] == [("A", "train"), ("B", "train"), ("C", "test"), ("D", "train"),
                                                   ("BC", "dev"), ("CD", "test"), ("DC", "test")]
    assert all(c.split == hash_split(c.id, fractions, "fingerspelling") for c in clips)
    words = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=3, max_letters=3)).listing().clips
    assert [(c.id, c.text, c.gloss) for c in words[4:]] == [("ase-spelled-000", "BA", "B A"),
                                                            ("ase-spelled-001", "CD", "C D"),
                                                            ("ase-spelled-002", "CDC", "C D C")]
    frames = {c.text: int(c.get("frames")) for c in words}
    assert [int(c.get("frames")) for c in words[4:]] == [frames["B"] + frames["A"], frames["C"] + frames["D"],
                                                         2 * frames["C"] + frames["D"]]
    letter = {c.text: c.media for c in words[:4]}
    assert words[6].get("letter_paths") == "|".join(letter[x] for x in "CDC") and words[6].media == "ase"
    assert spelled_paths(words[6], tmp_path) == [tmp_path / letter[x] for x in "CDC"]


def test_spelled_clip_without_letter_paths_is_refused_naming_the_clip(tmp_path):
    clip = Clip(id="ase-spelled-007", corpus="fingerspelling", split="train", language="ase", signer="unknown",
                text="AB", gloss="A B", media="ase", fps=25.0, extra=(("media_kind", "spelled"),))
    with pytest.raises(CorpusError) as err:
        spelled_paths(clip, tmp_path)
    assert str(err.value) == "spelled clip ase-spelled-007 lists no letter_paths; re-list the fingerspelling corpus"
    one = Clip(**{**clip.__dict__, "extra": (("letter_paths", "ase/a.pose"),)})
    assert spelled_paths(one, tmp_path) == [tmp_path / "ase" / "a.pose"]


def _pose_data(points: np.ndarray, confidence: np.ndarray, fps: float) -> PoseData:
    return PoseData(points.astype(np.float32), confidence.astype(np.float32), fps, (("hand", points.shape[1]),),
                    640, 480)


def test_resample_interpolates_seen_points_and_takes_the_nearest_frame_otherwise():
    """Linear in time where both neighbouring frames see a point (its confidence too); nearest frame otherwise."""
    T = 5
    points = np.zeros((T, 2, 3))
    points[:, :, 0] = np.arange(T)[:, None] * 10.0  # x = 10 t
    confidence = np.tile([[0.2, 0.9]], (T, 1))
    confidence[:, 0] = [0.2, 0.6, 0.2, 0.6, 0.2]
    confidence[2, 1] = 0.0  # point 1 unseen at frame 2
    data = _pose_data(points, confidence, 25.0)
    up = resample(data, 50.0)
    assert up.points.shape == (10, 2, 3) and up.confidence.shape == (10, 2) and up.fps == 50.0
    assert up.points.dtype == np.float32 and up.confidence.dtype == np.float32
    np.testing.assert_allclose(up.points[:, 0, 0], [0, 5, 10, 15, 20, 25, 30, 35, 40, 40])  # the last frame held
    np.testing.assert_allclose(up.confidence[:, 0], [0.2, 0.4, 0.6, 0.4, 0.2, 0.4, 0.6, 0.4, 0.2, 0.2], rtol=1e-6)
    # point 1 at frames 1.5 and 2.5 has one unseen neighbour: nearest frame (2 and 3), not a blend
    np.testing.assert_allclose(up.points[[3, 5], 1, 0], [20.0, 30.0])
    np.testing.assert_allclose(up.confidence[[3, 4, 5], 1], [0.0, 0.0, 0.9])
    np.testing.assert_allclose(up.confidence[[1, 7], 1], [0.9, 0.9])
    assert resample(data, 25.0) is data
    near = resample(_pose_data(np.zeros((100, 1, 3)), np.ones((100, 1)), 25.0), 25.5)  # a small rate change
    assert near.points.shape[0] == 102 and near.fps == 25.5
    down = resample(_pose_data(np.zeros((3, 1, 3)), np.ones((3, 1)), 50.0), 10.0)
    assert down.points.shape[0] == 1  # never fewer than one frame


# ----------------------------------------------------------------------------------------- .pose collections (2)
def test_truncated_pose_body_error_names_the_file_the_failure_and_the_fix(tmp_path, ase_rows):
    data = (lexicon_root() / ase_rows[0]["path"]).read_bytes()
    path = tmp_path / "cut.pose"
    path.write_bytes(data[: len(data) - 1000])  # header intact, the body cut short
    with pytest.raises(CorpusError) as err:
        read_pose(path)
    message, cause = str(err.value), err.value.__cause__
    assert cause is not None
    assert message.startswith(f"{path}: unreadable or truncated .pose file ({type(cause).__name__}: {cause})")
    assert message.endswith("; re-export it")
    with pytest.raises(CorpusError, match="does not exist; check the corpus root"):
        read_pose(tmp_path / "none.pose")


def test_pose_index_header_and_empty_fields_are_reported_naming_file_row_and_clip(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    index = tmp_path / "index.csv"
    index.write_text("id,path,label\na,a.pose,0\n", encoding="utf-8")
    with pytest.raises(CorpusError) as err:
        PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert str(err.value) == (f"{index} line 1: columns ['id', 'path', 'label'] lack ['split', 'text', 'language', "
                              "'signer']; expected id,path,split,text,language,signer and optional label")
    index.write_text("id,path,split,text,language,signer,label\na,a.pose,train,A,ase,s0,7\nnopath,,train,B,ase,s0,1\n"
                     ",a.pose,dev,C,ase,s0,2\nb,a.pose,dev,A,ase,s0,\nc,a.pose,test,A,ase,s0,-1\n", encoding="utf-8")
    listing = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert [(c.id, c.split, c.label) for c in listing.clips] == [("a", "train", 7), ("b", "dev", None),
                                                                  ("c", "test", -1)]
    assert listing.quarantined == (Quarantined("index.csv", 3, "nopath", "empty id or path"),
                                   Quarantined("index.csv", 4, None, "empty id or path"))


def test_pose_index_gloss_column_is_read_into_the_clip(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer,gloss\n"
                                        "a,a.pose,dev,hello,ase,s2,HELLO WORLD\n", encoding="utf-8")
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing().clips
    assert (clip.text, clip.gloss, clip.split, clip.corpus) == ("hello", "HELLO WORLD", "dev", "posefile")


def test_letter_rows_without_a_path_are_quarantined(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters[:1], (",en,ase,0,100,J,J,0", "  ,en,ase,0,100,K,K,0"))
    out = Collector(tmp_path)
    assert [x.letter for x in FingerspellingCorpus(tmp_path).table(out)] == ["A"]
    malformed = "malformed row: empty signed_language, words or path, or extra columns"
    assert out.listing().quarantined == (Quarantined("data.csv", 3, None, malformed),
                                         Quarantined("data.csv", 4, None, malformed))


def test_letter_and_word_clips_say_which_they_are(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters)
    clips = FingerspellingCorpus(tmp_path, FingerspellingConfig(words_per_language=2, max_letters=3)).listing().clips
    assert [c.get("clip_type") for c in clips] == ["letter"] * 4 + ["spelled"] * 2
    assert [c.get("media_kind") for c in clips] == ["pose"] * 4 + ["spelled"] * 2


def test_letter_clips_with_another_point_layout_anywhere_in_the_word_are_refused():
    hand = _pose_data(np.zeros((2, 2, 3)), np.ones((2, 2)), 25.0)
    other = PoseData(np.zeros((3, 2, 3), np.float32), np.ones((3, 2), np.float32), 25.0, (("face", 2),), 640, 480)
    for parts in ([hand, other], [hand, hand, other]):
        with pytest.raises(CorpusError) as err:
            concatenate(parts)
        assert str(err.value) == ("letter clips have different point layouts (hand:2 vs face:2); they cannot be "
                                  "concatenated")
    word = concatenate([hand, hand, hand])
    assert word.points.shape == (6, 2, 3) and word.confidence.shape == (6, 2) and word.fps == 25.0
    with pytest.raises(ValueError, match="the word has no letters"):
        concatenate([])


def test_fingerspelling_may_spell_one_letter_words_into_one_split(tmp_path, ase_letters):
    _letter_table(tmp_path, ase_letters)
    cfg = FingerspellingConfig(words_per_language=3, min_letters=1, max_letters=1, split_fractions=(1.0, 0.0, 0.0))
    clips = FingerspellingCorpus(tmp_path, cfg).listing().clips
    words = [c for c in clips if "spelled" in c.id]
    assert len(words) == 3 and all(len(c.text) == 1 for c in words)
    assert {c.split for c in clips} == {"train"}
    assert {c.corpus for c in clips} == {"fingerspelling"} and {c.language for c in clips} == {"ase"}
    for bad in ({"min_letters": 0}, {"min_letters": 3, "max_letters": 2}, {"words_per_language": -1}):
        with pytest.raises(ValueError) as err:
            FingerspellingConfig(**bad)
        assert "need words_per_language >= 0 and 1 <= min_letters <= max_letters" in str(err.value)
    with pytest.raises(ValueError, match=r"option corpora.fingerspelling.split_fractions: .*got \(0.5, 0.5, 0.5\)"):
        FingerspellingConfig(split_fractions=(0.5, 0.5, 0.5))


def _pose_v0_1(path: Path, frames: int) -> None:
    """A ``.pose`` file of the format's version 0.1 (pose-format ``PoseBody.read_v0_1``: fps and frame count as
    ushorts, a ushort person count, then float32 data (T, P, K, D) and confidence (T, P, K)), one OpenPose hand."""
    import io as _io

    pose = _openpose_hand_pose(frames, None)
    buffer = _io.BytesIO()
    pose.header.write(buffer)
    header = bytearray(buffer.getvalue())
    header[:4] = struct.pack("<f", 0.1)
    data = np.ma.getdata(pose.body.data).astype(np.float32)
    body = struct.pack("<HHH", 25, frames, 1) + data.tobytes() + np.asarray(pose.body.confidence, np.float32).tobytes()
    path.write_bytes(bytes(header) + body)


def test_a_version_0_1_pose_file_holds_one_person(tmp_path):
    _pose_v0_1(tmp_path / "old.pose", 4)
    info = read_pose_info(tmp_path / "old.pose")
    assert (info.frames, info.people, info.fps, round(info.version, 3)) == (4, 1, 25.0, 0.1)
    (clip,) = PoseFileCorpus(tmp_path, PoseFileConfig()).listing().clips
    assert dict(clip.extra)["people"] == "1" and dict(clip.extra)["frames"] == "4"


def test_pose_index_row_with_too_many_columns_is_quarantined_naming_its_id(tmp_path, ase_rows):
    shutil.copyfile(lexicon_root() / ase_rows[0]["path"], tmp_path / "a.pose")
    (tmp_path / "index.csv").write_text("id,path,split,text,language,signer\na,a.pose,train,A,ase,s0\n"
                                        "abc,a.pose,dev,B,ase,s0,extra\n,a.pose,dev,C,ase,s0,extra\n",
                                        encoding="utf-8")
    listing = PoseFileCorpus(tmp_path, PoseFileConfig(index="index.csv")).listing()
    assert [c.id for c in listing.clips] == ["a"]
    assert listing.quarantined == (Quarantined("index.csv", 3, "abc", "malformed row: wrong number of columns"),
                                   Quarantined("index.csv", 4, None, "malformed row: wrong number of columns"))


@pytest.mark.parametrize(("fps", "people", "message"), [
    (0.0, 1, "frame rate is 0.0"), (float("nan"), 1, "frame rate is nan"), (-25.0, 1, "frame rate is -25.0"),
    (5000.0, 1, "frame rate is 5000.0"), (25.0, 0, "no person")])
def test_a_pose_header_with_no_frame_rate_or_no_person_is_refused_by_every_reader(tmp_path, fps, people, message):
    """A v0.2 header stores fps, frames and people right after the components. Every duration, resampling and
    DTW window derives from fps, so 0, NaN, negative or above a camera's rate is refused, naming the file, by the
    header reader, the decoder and the tracker; so is a header that declares no person. The real file reads."""
    from m3t.corpora.posefile import _header
    from m3t.trackers.posefile import PoseFileError, load_pose_track

    source = next(lexicon_root().rglob("*.pose"))
    _, reader = _header(source)
    raw = bytearray(source.read_bytes())
    assert struct.unpack_from("<fIH", raw, reader.read_offset)[::2] == (25.0, 1)
    assert read_pose(source).fps == read_pose_info(source).fps == 25.0
    frames = struct.unpack_from("<fIH", raw, reader.read_offset)[1]
    struct.pack_into("<fIH", raw, reader.read_offset, fps, frames, people)
    path = tmp_path / "edited.pose"
    path.write_bytes(bytes(raw))
    for read in (read_pose_info, read_pose, load_pose_track):
        with pytest.raises((CorpusError, PoseFileError), match=message) as err:
            read(path)
        assert str(path) in str(err.value), read.__name__
