"""The batched FetchAttr gridworld, its instruction language and the expert describers (pure numpy).

Importing this package registers the Gymnasium ids HIGhER/FetchAttr-v0 and HIGhER/FetchAttr-Small-v0
when gymnasium is installed; without gymnasium everything else works the same.
"""
from higher_dist.world.grid import BatchedFetchAttr, StepResult
from higher_dist.world.objects import ObjectSpace

try:
    from higher_dist.world.gym_env import register_gym_envs
    register_gym_envs()
except ImportError:  # gymnasium is optional; gym_env itself re-raises any other broken import
    pass

__all__ = ["BatchedFetchAttr", "ObjectSpace", "StepResult"]
