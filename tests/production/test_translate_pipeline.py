"""``m3t translate`` on the tiny pipeline's checkpoints (:mod:`tiny_pipeline`): a parameter file, a real
fingerspelling ``.pose`` clip (spoken-to-signed's lexicon, tracked by MediaPipe Holistic) end to end through
fitting and tokens, and a short video the test writes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cli.main import main as cli_main
from m3t.production.produce import ProductionError, produce
from m3t.production.translate import input_kind, translate_input


def test_a_parameter_file_is_translated_by_the_smlm_and_the_judge(tiny_workspace, body, tmp_path):
    params = tiny_workspace.params
    produce("sentence 2", "ASL-SYN", params, "retrieval", tmp_path, name="s2", video=False, body=body)
    result = translate_input(tmp_path / "s2.npz", "ASL-SYN", params, body)
    assert result.kind == "parameters" and result.frames > 0
    assert isinstance(result.smlm, str) and isinstance(result.judge, str)
    assert list(result.seconds) == ["tokens", "smlm", "judge"] and all(s >= 0 for s in result.seconds.values())
    assert translate_input(tmp_path / "s2.npz", "ASL-SYN", params, body, judge=False).judge is None


def test_a_real_pose_clip_end_to_end(tiny_workspace, body, capsys):
    from m3t.corpora.fingerspelling import lexicon_root

    clip = min(lexicon_root().glob("*/*.pose"))
    assert cli_main(["--params", str(tiny_workspace.params_file), "translate", str(clip), "--language",
                     "ASL-SYN"]) == 0
    printed = capsys.readouterr().out
    assert f"{clip} (pose, " in printed and "  SMLM:  " in printed and "  judge: " in printed
    time_line = next(line for line in printed.splitlines() if line.startswith("  time: "))
    assert [part.split()[0] for part in time_line[len("  time: "):].split(", ")] == [
        "tracking", "fitting", "tokens", "smlm", "judge"]


def test_a_video_without_a_signer_fails_clearly(tiny_workspace, body, tmp_path):
    """A grey video without a person: MediaPipe tracks every frame and finds no landmark; the run ends in a clear
    error naming the file, not a traceback."""
    import cv2

    path = tmp_path / "grey.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (64, 64))
    for k in range(12):
        writer.write(np.full((64, 64, 3), 100 + k, np.uint8))
    writer.release()
    with pytest.raises(ProductionError, match=r"grey\.mp4: cannot fit the body model to its track \(the track has "
                                              r"no visible landmark .*\); is a signer visible\?"):
        translate_input(path, "ASL-SYN", tiny_workspace.params, body, judge=False)


def test_inputs_refused_by_name(tiny_workspace, body, tmp_path):
    (tmp_path / "clip.txt").write_text("x")
    with pytest.raises(ProductionError, match=r"clip\.txt: cannot translate a \.txt file; give a video"):
        input_kind(tmp_path / "clip.txt")
    with pytest.raises(ProductionError, match=r"nowhere\.pose does not exist"):
        translate_input(tmp_path / "nowhere.pose", "ASL-SYN", tiny_workspace.params, body)
    np.savez(tmp_path / "bad.npz", body=np.zeros((3, 2), np.float32))
    with pytest.raises(ProductionError, match=r"bad\.npz: no arrays \["):
        translate_input(tmp_path / "bad.npz", "ASL-SYN", tiny_workspace.params, body)
    with pytest.raises(ProductionError, match=r"unknown language 'XSL'"):
        translate_input(tmp_path / "bad.npz", "XSL", tiny_workspace.params, body)
    assert input_kind(Path(tmp_path)) == "frames"
