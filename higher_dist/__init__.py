"""higher-dist: HIGhER (Hindsight Generation for Experience Replay) as a distributed actor-learner system."""

try:  # registers the Gymnasium ids HIGhER/FetchAttr-v0 and -Small-v0 when gymnasium is installed
    import higher_dist.world  # noqa: F401
except ImportError:  # never let an optional extra break `import higher_dist`
    pass
