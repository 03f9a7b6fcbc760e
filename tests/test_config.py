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
