"""Sizes checked for every env family (lmac_env.sizes): an env's first reset and steps are
written into probe batches sized by its schema, and a schema that does not fit is refused in one
line naming the schema file, the field and both numbers (never a numpy traceback from inside the
env). `sized_toy` (tests/python/sized_toy.py) is an env whose real sizes are in its variant name."""
import numpy as np
import pytest

from lmac_env.core import Batch
from lmac_env.registry import make
from lmac_env.server import Driver, Meta, _random_actions
from lmac_env.sizes import SizeChecked, SizeMismatch, check

TRUE = dict(n_agents=2, obs_dim=5, state_dim=7, n_actions=4)
VARIANT = "a2-o5-s7-n4"


def schema_text(name, n_agents, obs_dim, state_dim, n_actions, episode_limit=10):
    """A schema the Rust side accepts too (the CLI tests run `lmac` on it)."""
    actions = ", ".join(f'"action {k}"' for k in range(n_actions))
    return (f'name = "{name}"\ntask = "Toy."\nn_agents = {n_agents}\nobs_dim = {obs_dim}\n'
            f'state_dim = {state_dim}\nn_actions = {n_actions}\nepisode_limit = {episode_limit}\n'
            f'message_columns = 0\nalpha = 0.1\nreward = "1 per step."\nactions = [{actions}]\n\n'
            f'[[obs_dims]]\ncount = {obs_dim}\nmeaning = "value {{k}}"\n\n'
            f'[[state_dims]]\ncount = {state_dim}\nmeaning = "value {{k}}"\n')


def write_schema(schema_dir, variant=VARIANT, **wrong):
    sizes = dict(TRUE, **wrong)
    path = schema_dir / "sized_toy" / f"{variant}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(schema_text(f"sized_toy:{variant}", **sizes))
    return path


@pytest.fixture
def schemas(tmp_path, monkeypatch):
    monkeypatch.setenv("LMAC_SCHEMA_DIR", str(tmp_path))
    return tmp_path


def refused(schemas, variant=VARIANT, **wrong):
    path = write_schema(schemas, variant, **wrong)
    with pytest.raises(SizeMismatch) as e:
        check(f"sized_toy:{variant}")
    text = str(e.value)
    assert "\n" not in text and text.startswith(f"{path}: "), text
    return text[len(str(path)) + 2:]


def test_a_fitting_schema_passes(schemas):
    write_schema(schemas)
    assert check(f"sized_toy:{VARIANT}").obs_dim == 5


@pytest.mark.parametrize("field,schema_says,words", [
    ("obs_dim", 4, "obs_dim = 4 but the env's observation has 5 values"),
    ("obs_dim", 6, "obs_dim = 6 but the env's observation has 5 values"),
    ("state_dim", 6, "state_dim = 6 but the env's state has 7 values"),
    ("state_dim", 9, "state_dim = 9 but the env's state has 7 values"),
    ("n_actions", 3, "n_actions = 3 but the env's available-action rows have 4 entries"),
    ("n_agents", 1, "n_agents = 1 but the env writes observations of at least 2 agents"),
    ("n_agents", 3, "n_agents = 3 but the env writes observations of 2 agents"),
])
def test_each_size_mistake_names_the_field_and_both_numbers(schemas, field, schema_says, words):
    assert refused(schemas, **{field: schema_says}).startswith(words)


def test_a_step_that_leaves_truncated_unwritten_is_refused(schemas):
    text = refused(schemas, variant=VARIANT + "-notrunc")
    assert text.startswith("step left truncated[0] unwritten"), text


def test_the_checked_first_calls_change_nothing_the_env_writes():
    """The env server runs its first reset and step through the probe and copies the rows into the
    slot: the rows and the env's own state match an unchecked run exactly."""
    rows = []
    for wrap in (False, True):
        env = make("lbf:8x8-2p-2f-s1-coop", 3, seed=5)
        out, meta = Batch.allocate(env.schema, 3), Meta.allocate(env.schema, 3)
        drv = Driver(SizeChecked(env) if wrap else env, 0)
        drv.first(out, meta)
        rng = np.random.default_rng(0)
        acts = np.zeros((3, 2), np.int32)
        seen = []
        for _ in range(30):
            _random_actions(rng, out.avail, acts)
            drv.advance(acts, out, meta)
            seen.append(np.concatenate([out.obs.ravel(), out.state.ravel(), out.avail.ravel(), out.reward,
                                        out.terminated, out.truncated, meta.flags]))
        rows.append(np.stack(seen))
    assert np.array_equal(rows[0], rows[1])


def test_a_wrapped_env_keeps_its_own_attributes():
    env = make("lbf:8x8-2p-2f-s1-coop", 2, seed=0)
    assert SizeChecked(env).envs is env.envs
