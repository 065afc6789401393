"""Closed-loop parking scenarios: scenario files, the other road users' behaviours, and the episode scorecard.

A pure library (no rendering): ``spec`` reads and writes scenario files and sets, ``resolve`` makes a scenario
concrete on its scene's map, ``behaviours`` and ``world`` move the actors, ``score`` grades an episode from its
log, ``shapes`` holds the footprint geometry they share. docs/scenarios.md describes the format and the card.
"""

from .behaviours import BEHAVIOURS, ActorState, Behaviour, make_behaviour
from .make import make_set
from .resolve import Setup, prepare
from .score import EpisodeLog, Scorecard, aggregate, score_episode
from .spec import (
    ActorSpec,
    Scenario,
    ScenarioError,
    ScenarioSet,
    dump_scenario,
    load_scenario,
    load_scenarios,
    load_set,
    scenario_schema,
    write_set,
)
from .world import Prediction, World, ego_actor

__all__ = ["Scenario", "ActorSpec", "ScenarioError", "ScenarioSet", "load_scenario", "dump_scenario", "load_set",
           "write_set", "load_scenarios", "scenario_schema", "Setup", "prepare", "ActorState", "Behaviour",
           "BEHAVIOURS", "make_behaviour", "World", "Prediction", "ego_actor", "EpisodeLog", "Scorecard",
           "score_episode", "aggregate", "make_set"]
