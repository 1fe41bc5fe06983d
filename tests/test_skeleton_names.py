"""The map between our bone names and OpenSim body names."""

from __future__ import annotations

import pytest

from bonecap.errors import InputError
from bonecap.skeleton.names import bones_of_body, model_family, opensim_body_map, opensim_body_of
from bonecap.skeleton.opensim import read_osim


@pytest.mark.parametrize("file,family", [
    ("Rajagopal2016.osim", "rajagopal2016"),
    ("gait2392_thelen2003muscle.osim", "gait2392"),
    ("FullBodyModel_Hamner2010_v2_0.osim", "hamner2010"),
])
def test_every_model_body_is_mapped(shared_data, file, family):
    assert model_family(file) == family
    skel = read_osim(shared_data / "bones/opensim/models" / file, load_meshes=False)
    assert set(skel.names) == set(opensim_body_map(family))


def test_lookups():
    assert opensim_body_of("hip_l", "rajagopal2016") == "pelvis"
    assert opensim_body_of("t11", "rajagopal2016") == "torso"
    assert opensim_body_of("ray3_r", "rajagopal2016") == "hand_r"
    assert opensim_body_of("patella_r", "gait2392") == "tibia_r"
    assert opensim_body_of("humerus_r", "gait2392") == "torso"
    assert opensim_body_of("wing", "rajagopal2016") is None
    assert bones_of_body("pelvis", ["sacrum", "hip_r", "femur_r", "hip_l"], "rajagopal2016") == [
        "sacrum", "hip_r", "hip_l"]
    with pytest.raises(InputError):
        model_family("arm26.osim")
