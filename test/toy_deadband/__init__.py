"""A toy effect written the way a new effect is added to the package: three modules, one per home (``effect``: the
identification's catalogue entry, ``term``: the controller's compensation term, ``stage``: the simulated valve's
stage), and nothing edited elsewhere: ``install`` adds them to the three registries (``test_toy_effect`` does it for
one test at a time)."""
from __future__ import annotations

from . import effect, stage, term


def install(monkeypatch) -> None:
    """The dead band in the registries: the effect catalogue, the controller's terms and the simulated valve's chain
    (after the backlash, on the spool's path) with its switch."""
    from piezo_valve_ros.core.control import terms
    from piezo_valve_ros.core.identification import effects
    from piezo_valve_ros.core.sim import stages
    monkeypatch.setattr(effects, "CATALOGUE", effects.CATALOGUE + (effect.DeadBand,))
    monkeypatch.setattr(terms, "TERMS", terms.TERMS + (term.TERM,))
    at = [link.name for link in stages.CHAIN].index("backlash") + 1
    monkeypatch.setattr(stages, "CHAIN", stages.CHAIN[:at] + (stage.LINK,) + stages.CHAIN[at:])
    monkeypatch.setattr(stages, "STAGE_SWITCHES", stages.STAGE_SWITCHES + (stage.SWITCH,))
