from pathlib import Path

import pytest

from diffshadow.cli import main

REPO = Path(__file__).resolve().parents[1]


def test_install_profiles_honours_xdg_and_refuses_a_different_profile(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "cfg"))
    main(["install-profiles", "--source", str(REPO / "profiles")])
    link = tmp_path / "cfg" / "snakemake" / "local"
    assert link.is_symlink() and (link / "config.yaml").read_text() == (REPO / "profiles/local/config.yaml").read_text()
    main(["install-profiles", "--source", str(REPO / "profiles")])  # again: nothing to do, no error
    other = tmp_path / "other" / "snakemake" / "local"
    other.mkdir(parents=True)
    (other / "config.yaml").write_text("cores: 64\n")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "other"))
    with pytest.raises(SystemExit, match="exists and differs from .*local; remove it or pass --force"):
        main(["install-profiles", "--source", str(REPO / "profiles")])
    assert (other / "config.yaml").read_text() == "cores: 64\n"


def test_bad_input_is_one_line_without_traceback(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["prepare-volume", "--config-json", '{"volume": "missing.raw", "transfer_function": '
              '{"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 1}}',
              "--out", str(tmp_path / "v.zarr")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "missing.raw: no such file" in err
    assert not (tmp_path / "v.zarr").exists()
