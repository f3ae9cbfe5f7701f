"""The body factory (m3t.body.factory): the eyelids setting, an unknown model named, and the FLAME shape count handed to SMPL-FX."""
from __future__ import annotations

import pytest


def test_the_body_factory_reads_the_eyelids_setting_and_names_an_unknown_model(fx_files, tmp_path):
    from m3t.body.config import BodyConfig
    from m3t.body.factory import load_body_model
    from m3t.body.smplfx_build import SMPLFXFilesMissing

    cfg = BodyConfig(model="smplfx", smplx_path=str(fx_files.smplx), flame_path=str(fx_files.flame_npz),
                     flame_correspondence_path=str(fx_files.correspondence), eyelids_path=str(tmp_path / "lids"))
    with pytest.raises(SMPLFXFilesMissing, match=r"body\.eyelids_path = .*lids: not found"):
        load_body_model(cfg)
    with pytest.raises(ValueError, match="body.model 'smpl' unknown; allowed: anny, smplfx"):
        load_body_model(BodyConfig(model="smpl"))


@pytest.mark.slow
def test_the_body_factory_hands_the_flame_shape_count_to_smplfx_and_keeps_no_geometry_in_its_state(fx_files):
    from m3t.body.config import BodyConfig
    from m3t.body.factory import load_body_model

    cfg = BodyConfig(model="smplfx", smplx_path=str(fx_files.smplx), flame_path=str(fx_files.flame_npz),
                     flame_correspondence_path=str(fx_files.correspondence), flame_shape_dims=50)
    body = load_body_model(cfg)
    labels = body.layout.identity_labels
    assert len(labels) == 60 and labels[-1] == "flame_shape_049"  # 10 SMPL-X shapes + the 50 asked for
    # every buffer is rebuilt from the licensed files: a saved state would copy their geometry into checkpoints
    assert body.state_dict() == {} and len(list(body.buffers())) > 0
