"""The coupling a scene chooses is an object built once from `insertion.coupling`, with its own parameters
(refsim/constraints/coupling_models.py), read by detection (rings or not) and the events (release margin)."""

from __future__ import annotations

import pytest

from refsim.constraints.coupling_models import COUPLING_MODELS, PaperCoupling, RingCoupling
from refsim.scene import load_scene
from refsim.simulation.detection import Detector
from refsim.simulation.events import EventRules


@pytest.mark.parametrize("name, model", [("ring", RingCoupling), ("paper", PaperCoupling)])
def test_the_scene_key_chooses_the_coupling_object(name, model):
    scene = load_scene("cube", ["mesh.cells=[2, 2, 2]", f"insertion.coupling={name!r}"])
    chosen = scene.insertion.coupling_model
    assert type(chosen) is model and chosen.name == name
    assert COUPLING_MODELS[name] is model


def test_the_release_margin_is_the_rings_hysteresis_and_none_for_the_paper():
    d_i = 0.5e-3
    assert RingCoupling().retraction_margin(d_i) == 0.5 * d_i
    assert RingCoupling(retraction_hysteresis=0.25).retraction_margin(d_i) == 0.25 * d_i
    assert PaperCoupling().retraction_margin(d_i) == 0.0
    assert RingCoupling.rings and not PaperCoupling.rings


def test_the_key_lists_every_coupling_and_refuses_others():
    from refsim.scene.fields import FieldError

    with pytest.raises((FieldError, ValueError), match="coupling"):
        load_scene("cube", ["insertion.coupling='line'"])


@pytest.mark.parametrize("name", ["ring", "paper"])
def test_detection_and_events_read_the_one_object(name):
    from refsim.simulation import Simulation

    simulation = Simulation(load_scene("cube", ["mesh.cells=[2, 2, 2]", f"insertion.coupling={name!r}"]))
    (instrument,) = simulation.instruments
    assert isinstance(instrument.detector, Detector) and isinstance(instrument.event_rules, EventRules)
    assert instrument.detector.coupling == instrument.event_rules.coupling == COUPLING_MODELS[name]()
    assert instrument.detector.ring == (name == "ring")
