"""params.yaml -> frozen dataclasses: presets, unknown keys and wrong types stop with clear messages."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from m3t.config import ConfigError, load_params
from m3t.experiment import to_dict

ROOT = Path(__file__).resolve().parents[2]
PARAMS = ROOT / "params.yaml"


@pytest.mark.parametrize("preset", ["default", "tiny", "paper"])
def test_presets_load(preset):
    params = load_params(PARAMS, preset=preset)
    assert params.fitting.w_kp == 1.0 and params.fitting.w_acc == 0.5 and params.fitting.w_reg == 0.01
    with pytest.raises(dataclasses.FrozenInstanceError):
        params.fitting.iterations = 3  # type: ignore[misc]


def test_presets_differ_where_they_should():
    tiny, default, paper = (load_params(PARAMS, preset=p) for p in ("tiny", "default", "paper"))
    assert tiny.fitting.iterations < default.fitting.iterations < paper.fitting.iterations
    assert tiny.experiment.enabled is False


def test_paper_preset_is_the_papers_setup_and_the_default_keeps_its_own():
    """M3T Sec. 4.1 / App. C / App. 0.D: the three corpora, SMPL-FX, selection on every dev clip of every corpus,
    epochs that pass every frame, the reduced mBART text vocabulary (396M); params.yaml keeps the embedded run."""
    default, paper = (load_params(PARAMS, preset=p) for p in ("default", "paper"))
    assert paper.data.train_corpora == ("how2sign", "csl_daily", "phoenix14t")
    assert all(c in paper.corpora for c in paper.data.train_corpora)
    assert paper.body.model == "smplfx"
    assert paper.tokenizer_train.val_max_frames == 0 and paper.smlm_train.eval_max_clips == 0
    assert paper.tokenizer_train.windows_per_clip == 0
    assert paper.smlm.reduce_text_vocab and paper.smlm.text_model_path == paper.smlm.pretrained_path != ""
    assert (paper.tokenizer_train.lr, paper.tokenizer_train.epochs, paper.tokenizer_train.batch_size,
            paper.tokenizer_train.warmup_epochs, paper.tokenizer_train.min_lr) == (1e-4, 100, 8, 25, 1e-6)
    assert (paper.smlm_train.lr, paper.smlm_train.epochs, paper.smlm_train.batch_size, paper.smlm_train.min_lr,
            paper.smlm_train.translation_prob) == (2e-4, 200, 32, 1e-6, 0.5)
    assert default.data.train_corpora == ("synthetic",) and default.body.model == "anny"
    assert (default.tokenizer_train.windows_per_clip, default.tokenizer_train.val_max_frames,
            default.smlm_train.eval_max_clips, default.smlm.reduce_text_vocab) == (4, 2000, 64, False)


def write(tmp_path, data):
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_unknown_key_names_section_and_allowed_keys(tmp_path):
    data = yaml.safe_load(PARAMS.read_text())
    data["fitting"]["iteration"] = 10
    with pytest.raises(ConfigError, match=r"fitting\.iteration.*allowed keys in 'fitting'.*iterations"):
        load_params(write(tmp_path, data))


def test_unknown_section(tmp_path):
    data = yaml.safe_load(PARAMS.read_text())
    data["fiting"] = {}
    with pytest.raises(ConfigError, match="fiting.*allowed sections"):
        load_params(write(tmp_path, data))


@pytest.mark.parametrize(
    "section,key,value,message",
    [
        ("fitting", "iterations", "many", r"fitting\.iterations: expected an integer"),
        ("fitting", "lr", True, r"fitting\.lr: expected a number"),
        ("body", "model", "smplz", r"body\.model: 'smplz' is not allowed; expected one of 'anny', 'smplfx'"),
        ("fit_corpus", "workers", 1.5, r"fit_corpus\.workers: expected an integer"),
        ("experiment", "enabled", "yes", r"experiment\.enabled: expected bool"),
    ],
)
def test_wrong_types(tmp_path, section, key, value, message):
    data = yaml.safe_load(PARAMS.read_text())
    data[section][key] = value
    with pytest.raises(ConfigError, match=message):
        load_params(write(tmp_path, data))


def test_int_accepted_for_float_and_round_trip(tmp_path):
    data = yaml.safe_load(PARAMS.read_text())
    data["fitting"]["lr"] = 1
    params = load_params(write(tmp_path, data))
    assert params.fitting.lr == 1.0 and isinstance(params.fitting.lr, float)
    again = load_params(write(tmp_path, to_dict(params)))
    assert again == params


def test_missing_file_and_unknown_preset(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_params(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        load_params(PARAMS, preset="huge")


def test_dataclass_defaults_equal_the_default_preset():
    """A component built without params.yaml behaves like the default pipeline: every section's dataclass
    defaults equal params.yaml (paper sizes live in the paper preset, not in the defaults)."""
    from m3t.config import SECTIONS, build_section, section_class

    params = load_params(PARAMS)
    differ = []
    for name in SECTIONS:
        if name == "corpora":
            continue
        cls = section_class(name)
        built, default = getattr(params, name), build_section(cls, {}, name)
        differ += [f"{name}.{f.name}: dataclass {getattr(default, f.name)!r}, params.yaml {getattr(built, f.name)!r}"
                   for f in dataclasses.fields(cls) if getattr(default, f.name) != getattr(built, f.name)]
    assert not differ, "\n".join(differ)


def test_every_component_option_is_reachable_from_params():
    """MediaPipe, fusion and the data selection are sections of their own."""
    params = load_params(PARAMS, overrides={"mediapipe": {"static_image_mode": True}, "fusion": {"max_gap": 3},
                                            "data": {"train_corpora": ["synthetic", "fingerspelling"]}})
    job = params.fit_job("fingerspelling")
    assert job.mediapipe.static_image_mode is True and job.fusion.max_gap == 3
    assert [str(p) for p in params.data.shards_dirs] == ["data/shards/synthetic", "data/shards/fingerspelling"]
    assert str(params.data.generated) == "data/generated/synthetic+fingerspelling"


def test_every_params_field_has_its_section_class():
    """SECTIONS names each Params field's class by path; a path that drifts from the field's type fails here."""
    from m3t.config import SECTIONS, Params, section_class

    assert sorted(SECTIONS) == sorted(f.name for f in dataclasses.fields(Params))
    for f in dataclasses.fields(Params):
        if f.name != "corpora":
            assert section_class(f.name).__name__ == str(f.type).split(".")[-1], f.name


def _nodes(text: str) -> int:
    """Nodes of a file without aliases, counted on its parsed value (every dict key and value, list item and
    the containers themselves)."""
    def count(value) -> int:
        if isinstance(value, dict):
            return 1 + sum(count(k) + count(v) for k, v in value.items())
        if isinstance(value, list):
            return 1 + sum(count(v) for v in value)
        return 1
    return count(yaml.safe_load(text))


def _bomb(levels: int) -> str:
    """params.yaml with a "billion laughs" under a known key: ``fitting.iterations`` becomes a list of ``levels``
    + 1 lists, each holding ten aliases of the one before, so it expands to 10**levels leaves from a few hundred
    bytes."""
    items = ['&a0 ["lol"]'] + [f"&a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, levels + 1)]
    text, count = re.subn(r"(?m)^  iterations: 100 .*$", "  iterations: [" + ", ".join(items) + "]",
                          Path("params.yaml").read_text())
    assert count == 1
    return text


def _expanded(levels: int) -> int:
    """How many values :func:`_bomb`'s ``fitting.iterations`` adds once expanded, counted by hand: a list of ten
    aliases of level i - 1 is 1 + 10 n(i - 1) nodes (n(0) = 2: the list and "lol"), plus the outer list, where
    params.yaml had one number."""
    n = [2]
    for _ in range(levels):
        n.append(1 + 10 * n[-1])
    return sum(n)


def test_an_alias_bomb_is_refused_at_once_naming_the_file_and_the_cap(tmp_path, monkeypatch):
    """10**9 leaves under a known key: refused in well under a second before anything is built (unbounded, the
    same file ran ``load_params`` for minutes into a MemoryError); a legitimately large file passes once the
    named environment key is raised."""
    import time

    path = tmp_path / "params.yaml"
    path.write_text(_bomb(9))
    start = time.monotonic()
    plain = _nodes(Path("params.yaml").read_text())
    with pytest.raises(ConfigError, match=f"aliases expand to {plain + _expanded(9):,} values.*raise "
                       "M3T_YAML_MAX_NODES") as err:
        load_params(path)
    assert time.monotonic() - start < 1.0 and str(path) in str(err.value) and len(str(err.value)) < 400
    path.write_text(_bomb(4))  # 10**4 leaves: under the cap, then a clear type error with a short message
    with pytest.raises(ConfigError, match=r"fitting\.iterations: expected an integer, got list") as err:
        load_params(path)
    assert len(str(err.value)) < 400  # the value is named, not printed whole
    total = plain + _expanded(4)
    monkeypatch.setenv("M3T_YAML_MAX_NODES", str(total - 1))  # the count is exact: one less refuses it
    with pytest.raises(ConfigError, match=f"expand to {total:,} values, more than {total - 1:,}"):
        load_params(path)
    monkeypatch.setenv("M3T_YAML_MAX_BYTES", "100")
    with pytest.raises(ConfigError, match=r"bytes, more than 100 .*raise M3T_YAML_MAX_BYTES"):
        load_params(path)


def test_anchors_and_aliases_that_params_files_use_still_load(tmp_path):
    base = yaml.safe_load(Path("params.yaml").read_text())
    text = Path("params.yaml").read_text().replace("fitting:\n", "fitting: &fit\n", 1) + "\n# reuse\n"
    path = tmp_path / "params.yaml"
    path.write_text(text)
    assert to_dict(load_params(path)) == to_dict(load_params("params.yaml"))
    assert yaml.safe_load(text) == base
