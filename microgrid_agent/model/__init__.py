"""The scheduling model of the paper, one module per constraint family: units (3)-(7), storage (8)-(14), adjustable
loads (15)-(17), balance and grid (2), (18)-(21), objective (1); ``build`` assembles them into one MILP."""

from .build import (Model, build, first_stage_constraints, first_stage_of, first_stage_variables,
                    second_stage_constraints)
from .grid import dp_plus_of
from .index import Index
from .objective import objective, recourse, startup_cost
from .params import DeviationCost, Mismatch, Params
from .variables import FIRST_STAGE, SECOND_STAGE, variables

__all__ = ["FIRST_STAGE", "SECOND_STAGE", "DeviationCost", "Index", "Mismatch", "Model", "Params", "build",
           "dp_plus_of", "first_stage_constraints", "first_stage_of", "first_stage_variables", "objective", "recourse",
           "second_stage_constraints", "startup_cost", "variables"]
