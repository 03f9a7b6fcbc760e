import pytest

from diffshadow.config import ConfigError, run_config


def test_command_line_strings_take_the_type_the_schema_asks_for():
    """Snakemake's `--config finetune='{epochs: 60}'` gives the string '60': it means 60, as in a file. A string
    that is no number stays an error naming the key; a string the schema wants stays a string."""
    run = run_config({"finetune": {"epochs": "60", "lr": "3.0e-5", "enabled": "false"},
                      "lights": {"center": ["0", "0.3", "1"], "unseen": "16"}, "device": "auto"}, "--config")
    assert (run["finetune"]["epochs"], run["finetune"]["lr"], run["finetune"]["enabled"]) == (60, 3e-5, False)
    assert run["lights"]["center"] == [0, 0.3, 1] and run["lights"]["unseen"] == 16 and run["device"] == "auto"
    with pytest.raises(ConfigError, match=r"^--config: key diffusion.epochs: 'sixty' is not of type 'integer'$"):
        run_config({"diffusion": {"epochs": "sixty"}}, "--config")
    with pytest.raises(ConfigError, match=r"key lights.count"):
        run_config({"lights": {"count": "[1, 2]"}}, "--config")  # read as a list: still not an integer
    with pytest.raises(ConfigError, match=r"^--config: key scenes: 'tooth' is not of type 'array' "
                                          r"\(a list: \[tooth]\)$"):
        run_config({"scenes": "tooth"}, "--config")  # `--config scenes=tooth`: the line says how to write it
    with pytest.raises(ConfigError, match=r"key lights: .*'count:5' was unexpected.*\(YAML wants a space after the "
                                          r"colon: \{count: 5}\)$"):
        run_config({"lights": {"count:5": None}}, "--config")  # how YAML reads `--config lights={count:5}`


def test_a_number_written_1e_minus_6_is_a_number(tmp_path):
    """PyYAML reads YAML 1.1, where `1e-6` (no dot) is a string, and `density_scale: 1e-6` in a scene file failed the
    schema as '1e-06'; as in YAML 1.2 and JSON it is the number, in a scene file, a run config or `--config`."""
    from diffshadow.config import read_yaml

    (tmp_path / "scene.yaml").write_text("transfer_function: {density_scale: 1e-6, other: [2E3, .5e1, 1.0e-2, 1e]}\n")
    assert read_yaml(tmp_path / "scene.yaml") == {"transfer_function": {"density_scale": 1e-6,
                                                                         "other": [2000.0, 5.0, 0.01, "1e"]}}
    assert run_config({"finetune": {"lr": "3e-5"}}, "--config")["finetune"]["lr"] == 3e-5


def test_a_key_given_twice_and_a_yaml_mistake_are_named_with_their_line(tmp_path):
    """PyYAML keeps the last of two equal keys silently: of two `transfer_function:` blocks, the one a user edited
    could be the one ignored. A key given twice, at any depth, is refused naming both lines; a syntax error names
    its line and column and the problem (PyYAML's first line, "while scanning for the next token", said neither)."""
    from diffshadow.config import read_yaml

    cases = {
        "volume: a.raw\nvolume: b.raw\n": "line 2, column 1: key 'volume' given twice (first at line 1)",
        "transfer_function:\n  opacity: [[0, 0]]\n  color: []\n  opacity: [[1, 1]]\n":
            "line 4, column 3: key 'opacity' given twice (first at line 2)",
        "lights: {count: 8, count: 16}\n": "line 1, column 20: key 'count' given twice (first at line 1)",
        "transfer_function:\n\topacity: []\n": "line 2, column 1: found character '\\t' that cannot start any token",
        "lights: {count: 8\n": "line 2, column 1: expected ',' or '}', but got '<stream end>'",
    }
    for text, said in cases.items():
        (tmp_path / "s.yaml").write_text(text)
        with pytest.raises(ConfigError) as caught:
            read_yaml(tmp_path / "s.yaml")
        assert str(caught.value) == f"{tmp_path / 's.yaml'}: not valid YAML at {said}"
    (tmp_path / "s.yaml").write_text("a: {x: 1}\nb: {x: 2}\nc: [{x: 1}, {x: 2}]\n")  # equal keys in other mappings
    assert read_yaml(tmp_path / "s.yaml") == {"a": {"x": 1}, "b": {"x": 2}, "c": [{"x": 1}, {"x": 2}]}


def test_a_setting_added_at_its_old_behaviour_stays_out_of_the_params_so_finished_runs_rerun_nothing():
    """diffusion.precision and the four cuda_graph settings came after runs existed: at their defaults ("auto",
    which leaves a finished run's float32 or eager weights as they are; finetune's False) and at what those runs did
    (float32, no graph), a job's
    params are the JSON they had before them, and the job still reads those values; another value is in the params
    (a changed param reruns the job)."""
    import json

    from diffshadow.config import UNCHANGED_WHEN, as_json, changed_settings, load_run
    from diffshadow.diffusion.config import DiffusionConfig

    run = load_run(None)
    added = {key for name, key in UNCHANGED_WHEN if name == "diffusion"}
    assert added == {"precision", "cuda_graph"}
    for (name, key), values in UNCHANGED_WHEN.items():
        assert run[name][key] == values[0]  # the default is the first value left out
    params = json.loads(as_json(run, "diffusion", "siren"))
    assert not added & set(params["diffusion"]) and params["siren"] == run["siren"]
    assert {**params["diffusion"], **{key: run["diffusion"][key] for key in added}} == run["diffusion"]
    cfg = DiffusionConfig.from_config(params["diffusion"])
    assert (cfg.precision, cfg.cuda_graph) == ("auto", "auto")
    run["diffusion"].update(precision="bfloat16", cuda_graph=True)
    assert {key: json.loads(as_json(run, "diffusion"))["diffusion"][key] for key in added} == {
        "precision": "bfloat16", "cuda_graph": True}
    assert changed_settings("diffusion", {"cuda_graph": False, "lr": 1.0}) == {"lr": 1.0}
    assert changed_settings("diffusion", {"cuda_graph": "auto", "precision": "float32"}) == {}
    assert changed_settings("diffusion", {"precision": "auto"}) == {}
    assert changed_settings("diffusion", {"cuda_graph": 0}) == {"cuda_graph": 0}  # not False: the schema's error
    assert changed_settings("fit", {"cuda_graph": False}) == {}  # fit.cuda_graph came later: False before
    assert changed_settings("data_inr", {"cuda_graph": "auto"}) == {}  # and "auto" since a GPU timed it
    assert changed_settings("fit", {"precision": "float32"}) == {"precision": "float32"}  # another section's key
    assert "cuda_graph" not in json.loads(as_json(load_run(None), "fit"))["fit"]
    assert "cuda_graph" not in json.loads(as_json(load_run(None), "finetune"))["finetune"]  # False until timed
    assert changed_settings("finetune", {"cuda_graph": "auto"}) == {"cuda_graph": "auto"}  # graphs on CUDA: asked
    assert load_run(None)["diffusion"]["precision"] == "auto"  # a run's change stays in that run


def test_changing_one_run_config_leaves_the_defaults_of_the_next():
    """load_run's sections are the run's own: changing one in place (as a test or a script may) changed the cached
    defaults under every later config of the process, so a test's bfloat16 reached other tests' models."""
    from diffshadow.config import defaults, load_run

    run = load_run(None)
    run["diffusion"]["epochs"] = -1
    run["fit"]["lr"] = 99.0
    assert defaults()["diffusion"]["epochs"] != -1 and defaults()["fit"]["lr"] != 99.0
    assert load_run(None)["diffusion"]["epochs"] == defaults()["diffusion"]["epochs"]


def test_a_json_option_reads_inline_text_and_a_file_alike(tmp_path):
    """`--tf-json` and `--config-json` take an object's text or a file's path: the same dict either way, and a
    missing section's error names the file it came from."""
    import pytest

    from diffshadow.config import ConfigError, parse_json

    text = '{"opacity": [[0, 0], [1, 1]], "density_scale": 5}'
    (tmp_path / "tf.json").write_text(text)
    inline, from_file = parse_json(text, "--tf-json"), parse_json(str(tmp_path / "tf.json"), "--tf-json")
    assert inline == from_file == {"opacity": [[0, 0], [1, 1]], "density_scale": 5}
    with pytest.raises(ConfigError, match=r"--tf-json .*tf.json: no 'color' section"):
        from_file["color"]
    with pytest.raises(ConfigError, match=r"expected a JSON object or a file holding one, got '\[1\]'"):
        parse_json("[1]", "--tf-json")


def test_a_json_key_given_twice_is_refused_at_any_depth(tmp_path):
    """json keeps the last of two equal keys without a word; a hand-typed --config-json or --tf-json that repeats
    one is refused naming the key and where it came from, as the YAML reader refuses one in a run file. Equal keys
    in two objects are two keys."""
    import pytest

    from diffshadow.config import ConfigError, parse_json

    assert parse_json('{"fit": {"lr": 1}, "data_inr": {"lr": 2}}') == {"fit": {"lr": 1}, "data_inr": {"lr": 2}}
    with pytest.raises(ConfigError, match=r"^--config-json: key 'lr' given twice in one object$"):
        parse_json('{"fit": {"lr": 1e-4, "steps": 3, "lr": 1e-3}}')
    (tmp_path / "tf.json").write_text('{"opacity": [], "opacity": []}')
    with pytest.raises(ConfigError, match=r"^--tf-json \S*tf.json: key 'opacity' given twice in one object$"):
        parse_json(str(tmp_path / "tf.json"), "--tf-json")


def test_a_scene_without_a_file_lists_the_scenes_there_and_the_nearest_name(tmp_path):
    from diffshadow.config import scene_config

    for name in ("nucleon", "hydrogen_atom"):
        (tmp_path / f"{name}.yaml").write_text("{}\n")
    with pytest.raises(ConfigError, match=r"no file .*nucleonn\.yaml; did you mean nucleon\? \(the scenes there: "
                                          r"hydrogen_atom, nucleon\)$"):
        scene_config({}, "nucleonn", scenes_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"no file .*foo\.yaml \(the scenes there: hydrogen_atom, nucleon\)$"):
        scene_config({}, "foo", scenes_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"no file .*foo\.yaml$"):
        scene_config({}, "foo", scenes_dir=tmp_path / "empty")


def test_an_unknown_key_near_a_known_one_is_named_with_it():
    with pytest.raises(ConfigError, match=r"key fit: .*'stpes' was unexpected\) \(did you mean steps\?\)$"):
        run_config({"fit": {"stpes": 5}}, "config/config.yaml")
    with pytest.raises(ConfigError, match=r"key \(top level\): .*'lihgts' was unexpected\) \(did you mean lights\?\)$"):
        run_config({"lihgts": {"count": 4}}, "config/config.yaml")
    with pytest.raises(ConfigError, match=r"'zzz' was unexpected\)$"):  # nothing near: no guess
        run_config({"diffusion": {"zzz": 3}}, "config/config.yaml")
