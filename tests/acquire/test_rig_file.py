"""The rig file: parsing, defaults and every validation error naming its key."""

from __future__ import annotations

from pathlib import Path

import pytest

from mocaprig.acquire.davis240c_config import BiasPreset
from mocaprig.acquire.rig_file import RIG_FILE_VERSION, load_rig_file, parse_rig_file
from mocaprig.errors import ValidationError

_FULL = """\
format_version = 1

[session]
name = "lab-a"
notes = "two cameras"

[[d415]]
serial = "819612070593"
role = "master"
mode = "848x480@30"
exposure_us = 6000
gain = 32
laser_power_mw = 210
emitter = false

[[d415]]
serial = "819612070594"
role = "slave"

[davis]
serial = "02460045"
bias_preset = "pyaer"

[syncbox]
port = "/dev/ttyACM0"
mode = "generate"
rate_hz = 60
width_us = 200
"""


def test_full_rig_file_parses_with_values_and_defaults() -> None:
    rig = parse_rig_file(_FULL)
    assert rig.format_version == RIG_FILE_VERSION
    assert not rig.mock
    assert [c.serial for c in rig.d415] == ["819612070593", "819612070594"]
    master, slave = rig.d415
    assert rig.master is master
    assert (master.options.exposure_us, master.options.gain) == (6000, 32)
    assert (master.options.laser_power_mw, master.options.emitter_enabled) == (210, False)
    assert str(slave.stream) == "848x480@30"
    assert slave.options.exposure_us == 8500  # default
    assert rig.davis is not None
    assert rig.davis.bias_preset is BiasPreset.PYAER
    assert rig.syncbox is not None
    assert (rig.syncbox.mode, rig.syncbox.rate_hz, rig.syncbox.width_us) == ("generate", 60, 200)
    meta = rig.metadata()
    assert meta["d415.0.serial"] == "819612070593"
    assert meta["d415.1.role"] == "slave"
    assert meta["davis.bias_preset"] == "pyaer"
    assert meta["session_name"] == "lab-a"
    assert rig.text == _FULL


def test_load_reads_the_file_and_names_a_missing_one(tmp_path: Path) -> None:
    p = tmp_path / "rig.toml"
    p.write_text(_FULL)
    assert load_rig_file(p).source == str(p)
    with pytest.raises(ValidationError, match=r"nope\.toml cannot be read"):
        load_rig_file(tmp_path / "nope.toml")


def _replace(old: str, new: str) -> str:
    assert old in _FULL
    return _FULL.replace(old, new, 1)


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("format_version = 1\n[davis\n", "not valid TOML"),
        ("[davis]\nserial = '02460045'\n", "'format_version' is missing"),
        (_replace("format_version = 1", "format_version = 2"), "format_version 2 is not supported"),
        (_replace("format_version = 1", "format_version = 1\ncolour = 3"),
         "unknown key 'colour'; allowed keys: format_version, mock"),
        (_replace('notes = "two cameras"', "note = 'x'"), "unknown key 'session.note'"),
        (_replace('role = "slave"', 'role = "boss"'),
         r"'d415\[1\].role' = 'boss' is not allowed; choose one of \['master', 'slave'\]"),
        (_replace('role = "slave"', 'role = "master"'), "exactly one \\[\\[d415\\]\\] must have"),
        (_replace('serial = "819612070594"', 'serial = "819612070593"'), "listed more than once"),
        (_replace('serial = "819612070594"', "serial = 819612070594"),
         r"'d415\[1\].serial' must be str"),
        (_replace('serial = "819612070594"', 'serial = "8196"'), "12-digit D415 serial"),
        (_replace('mode = "848x480@30"', 'mode = "640x480@30"'),
         r"'d415\[0\].mode' = '640x480@30' is not allowed; choose one of \['848x480@30', "),
        (_replace('mode = "848x480@30"', 'mode = "1280x720@30"'), "same mode"),
        (_replace("gain = 32", "gain = 4"), r"d415\[0\] \(serial 819612070593\): gain"),
        (_replace("laser_power_mw = 210", "laser_power_mw = 200"), "multiple of 30"),
        (_replace("exposure_us = 6000", "exposure_us = 40000"), "exceeds the frame period"),
        (_replace("emitter = false", "emitter = 0"), r"'d415\[0\].emitter' must be bool"),
        (_replace('serial = "02460045"', 'serial = "123"'), "8-character DAVIS serial"),
        (_replace('bias_preset = "pyaer"', 'bias_preset = "fast"'),
         r"'davis.bias_preset' = 'fast' is not allowed; choose one of \['default', 'legacy'"),
        (_replace('mode = "generate"', 'mode = "drive"'),
         r"'syncbox.mode' = 'drive' is not allowed; choose one of \['listen', 'generate'\]"),
        (_replace("rate_hz = 60", "rate_hz = 5000"), r"'syncbox.rate_hz' = 5000 .* 1..1000"),
        (_replace("width_us = 200", "width_us = 9000"), r"'syncbox.width_us' = 9000 .* 10..8333"),
        (_replace('port = "/dev/ttyACM0"', ""), "'syncbox.port' is missing"),
        ("format_version = 1\n", "lists no device"),
        ("format_version = 1\nmock = 'yes'\n[davis]\nserial = '02460045'\n", "'mock' must be bool"),
        ("format_version = 1\nd415 = 3\n", "array of tables"),
    ],
)  # fmt: skip
def test_invalid_rig_files_name_the_key_and_the_allowed_values(text: str, pattern: str) -> None:
    with pytest.raises(ValidationError, match=pattern):
        parse_rig_file(text, source="rig.toml")


def test_mock_flag_and_davis_only_rig() -> None:
    rig = parse_rig_file("format_version = 1\nmock = true\n[davis]\nserial = '02460045'\n")
    assert rig.mock
    assert rig.d415 == ()
    assert rig.master is None
    assert rig.davis is not None
    assert rig.davis.bias_preset is BiasPreset.DEFAULT
