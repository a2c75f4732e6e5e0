"""Smart Start: the count model (:mod:`.counts`), UCB selection of S_ss (:mod:`.selection`), the value-iteration
planner (:mod:`.planner`), the frontier of tried moves (:mod:`.frontier`) and the controller of guided collection
(:mod:`.controller`)."""

from ss_drl.smart_start.controller import SmartStart
from ss_drl.smart_start.counts import CountModel
from ss_drl.smart_start.frontier import Frontier
from ss_drl.smart_start.planner import Plan, Planner
from ss_drl.smart_start.selection import select_smart_start, ucb_scores

__all__ = ["CountModel", "Frontier", "Plan", "Planner", "SmartStart", "select_smart_start", "ucb_scores"]
