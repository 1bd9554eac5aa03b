"""`lmac envs --check` and an env server through the real binary: every family's env is built and
compared with its schema, a size mistake is one line naming the file, the field and both numbers
(at `--check` and when a run's env server starts, not a numpy traceback), and a schema still
holding generated `EDIT:` placeholders is refused by `--check`."""
from test_pz_cli import run
from test_sizes import VARIANT, schema_text, write_schema

NAME = f"sized_toy:{VARIANT}"


def test_check_passes_a_fitting_schema_and_refuses_a_wrong_size(tmp_path):
    write_schema(tmp_path)
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert NAME in r.stdout
    assert "OK: 1 schema valid and finished" in r.stderr and "sizes match the environment for 1" in r.stderr, r.stderr
    path = write_schema(tmp_path, obs_dim=4)
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0
    assert f"{path}: obs_dim = 4 but the env's observation has 5 values" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    path = write_schema(tmp_path, n_actions=3)
    r = run(["envs", "--check"], tmp_path)
    assert f"{path}: n_actions = 3 but the env's available-action rows have 4 entries" in r.stderr, r.stderr


def test_check_refuses_edit_placeholders_naming_file_and_field(tmp_path):
    path = write_schema(tmp_path)
    path.write_text(path.read_text().replace('task = "Toy."', 'task = "EDIT: what the team must do"')
                    .replace('"action 2"', '"EDIT: action 2"'))
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0
    assert f"{path}: task, actions[2]: still the generated \"EDIT:\" placeholder" in r.stderr, r.stderr


def test_an_env_server_refuses_a_wrong_size_in_one_line(tmp_path):
    """The schema is valid to the Rust side (so the run starts); the env server's first reset
    finds that the env writes 5 observation values where the schema says 6."""
    path = write_schema(tmp_path, obs_dim=6)
    r = run(["run", "--env", NAME, "--envs", "2", "--steps", "40"], tmp_path)
    assert r.returncode != 0
    assert f"{path}: obs_dim = 6 but the env's observation has 5 values (seen in reset)" in r.stderr, r.stderr[-3000:]
    assert "Traceback" not in r.stderr, r.stderr[-3000:]


def test_generate_for_a_family_whose_module_gives_its_sizes(tmp_path):
    """Not only pz: any family module with sizes(variant) (here the worked example); the schema
    is then refused by --check until its EDIT texts are written, and fits the env after."""
    name = "lmac_env.examples.meet:line5-2ag"
    r = run(["envs", "--generate", name], tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"{name}: 2 agents, obs 6, state 2, actions 3, episode limit 20, message columns 8" in r.stdout
    path = tmp_path / "lmac_env.examples.meet" / "line5-2ag.toml"
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0 and f"{path}: task, reward, actions[0], actions[1] and 3 more" in r.stderr, r.stderr
    path.write_text(path.read_text().replace("EDIT: ", ""))
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode == 0, r.stderr
    r = run(["envs", "--generate", name], tmp_path)
    assert r.returncode != 0 and "--force" in r.stderr, "an existing schema is not overwritten"


def test_generate_names_what_is_missing_when_a_module_cannot_say_its_sizes(tmp_path):
    r = run(["envs", "--generate", NAME], tmp_path)
    assert r.returncode != 0
    assert "module sized_toy has no sizes(variant)" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_family_no_module_makes_fails_check_and_run_in_one_line(tmp_path):
    """A typo in the family (or its folder off the env servers' PYTHONPATH) is not skipped by
    --check: the run would fail the same way. The env server says so in one line."""
    from test_sizes import TRUE

    path = tmp_path / "no_such_family_zz" / f"{VARIANT}.toml"
    path.parent.mkdir(parents=True)
    path.write_text(schema_text(f"no_such_family_zz:{VARIANT}", **TRUE))
    r = run(["envs", "--check"], tmp_path)
    assert r.returncode != 0
    assert f"{path}: no module makes family 'no_such_family_zz'" in r.stderr, r.stderr
    r = run(["run", "--env", f"no_such_family_zz:{VARIANT}", "--envs", "2", "--steps", "40"], tmp_path)
    assert r.returncode != 0
    assert "unknown environment family 'no_such_family_zz'" in r.stderr, r.stderr[-3000:]
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
