"""A checkpoint written by another version's model (other shapes) is refused on resume with a message that
names the file, never a torch traceback from inside a role."""
from __future__ import annotations

import pytest

from higher_dist.config_presets import make_config
from higher_dist.learning.agent import AgentBuilder
from higher_dist.roles.relabeler import RelabelerService, restore
from higher_dist.rundir import RunDir
from higher_dist.wire.sockets import RejectCounter


def service(**overrides) -> RelabelerService:
    return RelabelerService(AgentBuilder(make_config("higher", "small", **overrides)), RejectCounter())


def test_the_relabeler_resumes_its_own_checkpoint_and_refuses_one_of_other_shapes(tmp_path):
    rd = RunDir(tmp_path)
    assert restore(service(), rd) is False  # nothing to resume
    rd.save_checkpoint("relabeler", service().state_dict())
    assert restore(service(), rd) is True
    # The same run's checkpoint, read by a generator whose context layer is wider (as another version's).
    with pytest.raises(ValueError, match=r"relabeler\.ckpt does not fit this version's generator, start a new run"):
        restore(service(**{"generator.hidden": 64}), rd)
