from __future__ import annotations

from pathlib import Path

import pytest

from app.core.config import DEFAULT_CONFIG_FILE, AppConfig, ConfigError, load_config


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_default_file_matches_the_built_in_defaults() -> None:
    assert load_config(DEFAULT_CONFIG_FILE) == AppConfig()


def test_partial_override_keeps_other_defaults(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "devices:\n  linarm:\n    mode: serial\n    port: /dev/ttyACM0\n"))
    assert cfg.devices.linarm.mode == "serial"
    assert cfg.devices.linarm.port == "/dev/ttyACM0"
    assert cfg.devices.linarm.baudrate == 460800
    assert cfg.devices.physio == AppConfig().devices.physio


def test_unknown_key_is_refused_with_key_and_line(tmp_path: Path) -> None:
    path = write(tmp_path, "version: 1\ndevices:\n  linarm:\n    mode: simulated\n    baud_rate: 9600\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert err.value.line == 5
    assert err.value.key == "devices.linarm.baud_rate"
    assert f"{path}:5" in str(err.value) and "unknown key" in str(err.value)


def test_bad_value_is_refused_with_key_and_line(tmp_path: Path) -> None:
    path = write(tmp_path, "safety:\n  fes:\n    max_current_ma: 300\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert (err.value.line, err.value.key) == (3, "safety.fes.max_current_ma")
    assert "outside the allowed range" in str(err.value)


def test_wrong_type_and_bad_choice(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cfg.yaml:3: devices.linarm.baudrate: expected a whole number"):
        load_config(write(tmp_path, "devices:\n  linarm:\n    baudrate: fast\n"))
    with pytest.raises(ConfigError, match=r":3: devices.fes.protocol: expected one of 'sm1', 'sm2'"):
        load_config(write(tmp_path, "devices:\n  fes:\n    protocol: sm3\n"))


def test_invalid_yaml_names_the_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(write(tmp_path, "devices:\n  linarm: [1,\n  physio: 2\n"))
    assert err.value.line is not None and "not valid YAML" in str(err.value)


def test_cross_field_rules(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no port is given"):
        load_config(write(tmp_path, "devices:\n  linarm:\n    mode: serial\n"))
    with pytest.raises(ConfigError, match=r"position_min_m .* must be below"):
        load_config(write(tmp_path, "safety:\n  robot:\n    position_min_m: 0.4\n    position_max_m: 0.3\n"))


def test_main_refuses_a_malformed_config_and_starts_nothing(tmp_path: Path, capsys, monkeypatch) -> None:
    from PySide6.QtWidgets import QMessageBox

    import main

    # With a display (Xvfb in CI) the window path also shows the refusal in a dialog: record it
    # instead of blocking the test on a modal box.
    shown: list[str] = []
    monkeypatch.setattr(QMessageBox, "critical", staticmethod(lambda _parent, _title, text: shown.append(text)))
    code = main.main(["--config", str(write(tmp_path, "ui:\n  palette: neon\n"))])
    assert code == 2
    assert all("ui.palette" in text for text in shown)
    err = capsys.readouterr().err
    assert "nothing was started" in err and "ui.palette" in err and ":2:" in err
