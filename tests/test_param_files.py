"""Parameter files (issue 22): nothing is written that the file did not mean, files are
bounded, and every mistake is one line naming file:row, the address and the value.

The rules are checked on ``files.read`` directly (cheap), and end to end through
`abh3 param restore/diff/set` against a running simulated drive: each refused command
exits 2 and the drive hears no request at all — the file is checked before the bus is
used for it."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import CodecError
from abh3_supervisor.params import files, table
from abh3_supervisor.params.files import MAX_ROWS, ParamFileError, ParamValue
from abh3_supervisor.params.telabh3 import pack_float
from abh3_supervisor.runtime.bus_runtime import Runtime

MAKER_HEADER = "パラメータアドレス,パラメータ名,パラメータ値(表示値),パラメータ値(内部値)"


async def started(rt: Runtime) -> None:
    """Once a service's start-up check has read its drives: a tool with the same host
    address starting a transfer meanwhile would find the drive busy (docs/parameters.md)."""
    if rt.verifying is not None:
        await asyncio.wait_for(asyncio.shield(rt.verifying), 5)


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("cp932" if name.endswith(".csv") else "utf-8"))
    return path


# ------------------------------------------------------------ the values


BAD_ROWS = [
    # (CSV text, the message's expected fragment)
    (
        "20480,SPEED_AY_0,,4294967297\r\n",  # was written as 1 (masked to 32 bits)
        r"x.csv:1: 0x5000 SPEED_AY_0: internal value '4294967297' is beyond 32 bits",
    ),
    (
        "20480,SPEED_AY_0,,-99999999999\r\n",  # was written as 5.96e-36
        r"x.csv:1: 0x5000 SPEED_AY_0: internal value '-99999999999' is beyond 32 bits",
    ),
    ("20480,SPEED_AY_0,,0x1FFFFFFFF\r\n", r"internal value '0x1FFFFFFFF' is beyond 32 bits"),
    ("20480,SPEED_AY_0,,0o17\r\n", r"internal value '0o17' is not an integer"),
    ("20480,SPEED_AY_0,,4194312.0\r\n", r"internal value '4194312.0' is not an integer"),
    ("20480,SPEED_AY_0,nan,\r\n", r"x.csv:1: 0x5000 SPEED_AY_0: display value 'nan' is not finite"),
    ("20480,SPEED_AY_0,inf,\r\n", r"display value 'inf' is not finite"),
    ("20480,SPEED_AY_0,-Infinity,\r\n", r"display value '-Infinity' is not finite"),
    ("20480,SPEED_AY_0,1e999,\r\n", r"display value '1e999' is not finite"),
    ("20480,SPEED_AY_0,nan,4194312\r\n", r"display value 'nan' is not finite"),  # not "text"
    (
        "20480,SPEED_AY_0,,0x000FFFFF\r\n",  # the packed float's +inf code
        r"0x5000 SPEED_AY_0: internal value '0x000FFFFF' is inf as a packed float",
    ),
    ("20480,SPEED_AY_0,,1048576\r\n", r"internal value '1048576' is -inf as a packed float"),
    ("20480,SPEED_AY_0,,1000000\r\n", r"internal value '1000000' is nan as a packed float"),
    ("20480,SPEED_AY_0,1e80,\r\n", r"display value '1e80': 1e\+80 is beyond the packed-float"),
    ("20480,SPEED_AY_0,1e-80,\r\n", r"display value '1e-80': 1e-80 is beyond the packed-float"),
    (
        "16666,CAN_CONTROL_FLAG_LOGIC,4294967296,\r\n",
        r"0x411A CAN_CONTROL_FLAG_LOGIC: display value '4294967296': .* is not a 32-bit integer",
    ),
    ("16666,CAN_CONTROL_FLAG_LOGIC,1.5,\r\n", r"display value '1.5': 1.5 is not a 32-bit integer"),
    (
        "20480,SPEED_AY_0,800,4194313\r\n",  # 4194313 is 900
        r"0x5000 SPEED_AY_0: display value '800' and internal value '4194313' \(= 900\) disagree",
    ),
    ("20480,SPEED_AY_0,800 [min^-1],\r\n", r"display value '800 \[min\^-1\]' is not a number"),
    ("20480,SPEED_AY_0,,\r\n", r"x.csv:1: 0x5000 SPEED_AY_0: no value"),
    ("20480,SPEED_AY_1,800,\r\n", r"0x5000 SPEED_AY_0: named SPEED_AY_1, which is 0x5001"),
    # a first row with a typo is no header: it is an error (it was skipped)
    (
        "2048O,SPEED_AY_0,800,4194312\r\n20481,SPEED_AY_1,400,\r\n",
        r"x.csv:1: '2048O' is no address",
    ),
    ("address,name,value,word\r\n20480,SPEED_AY_0,800,\r\n", r"x.csv:1: 'address' is no address"),
    (
        "20480,SPEED_AY_0,800,\r\n20481,SPEED_AY_1,400,\r\n20480,SPEED_AY_0,900,\r\n",
        r"x.csv:3: 0x5000 SPEED_AY_0 is also on row 1: one value per address",
    ),
    ("30583,0x7777,5,5\r\n", r"x.csv:1: 0x7777 0x7777: not in the parameter table"),
    (
        "20480,A,Y speed,800,4194312\r\n",  # a name with a comma, unquoted: cells shift
        r"x.csv:1: 5 cells: expected address, name, display value, internal value",
    ),
    ("\x00\x00,x,1,\r\n", r"x.csv:1: '\\x00\\x00' is no address"),  # shown escaped
]


@pytest.mark.parametrize(("text", "message"), BAD_ROWS)
def test_each_mistake_is_named_with_file_row_address_and_value(
    tmp_path: Path, text: str, message: str
) -> None:
    with pytest.raises(ParamFileError, match=message):
        files.read(write(tmp_path, "x.csv", text), allow_unknown=False)


def test_what_a_file_means_is_read_exactly(tmp_path: Path) -> None:
    path = write(
        tmp_path,
        "ok.csv",
        "20480,SPEED_AY_0,800,0x00400008\r\n"  # hex internal value
        "16643,CAN_HOST_ADDRESS,-1,2097151\r\n"
        "16513,0x4081,-50 [℃],2097102\r\n"  # the maker's −50 (another encoding), a unit
        "16666,CAN_CONTROL_FLAG_LOGIC,-1,4294967295\r\n"  # unsigned internal, signed display
        "20865,DIGITAL_OUTPUT_1,-1,-1\r\n"  # signed internal value
        "20481,SPEED_AY_1,0.25,\r\n"  # display only: encoded by the kind
        "20482,SPEED_AY_2,1234567,\r\n"  # six significant digits, rounded
        "\r\n,,,\r\n"  # a blank line, an empty row: skipped
        "20484,SPEED_AY_4,26214400E+27,910426112\r\n"  # the maker's odd form, the same value
        "20485,SPEED_AY_5,CANホスト,2\r\n",  # a word for the value: not compared
    )
    with pytest.raises(ParamFileError, match=r"ok.csv:3: 0x4081 0x4081: not in the parameter"):
        files.read(path, allow_unknown=False)
    assert files.read(path, allow_unknown=True) == [
        ParamValue(0x5000, 0x00400008),
        ParamValue(0x4103, 0x001FFFFF),
        ParamValue(0x4081, 0x001FFFCE),
        ParamValue(0x411A, 0xFFFFFFFF),
        ParamValue(0x5181, 0xFFFFFFFF),
        ParamValue(0x5001, pack_float(0.25)),
        ParamValue(0x5002, pack_float(1234570)),
        ParamValue(0x5004, 910426112),
        ParamValue(0x5005, 2),
    ]


@pytest.mark.parametrize(
    "header",
    [
        MAKER_HEADER,  # as in the maker's public AGV file (wacogiken/ABH3_AI)
        '"パラメータアドレス","パラメータ名","パラメータ値(表示値)","パラメータ値(内部値)"',
        "address,name,display value,internal value",
        "Address, Name, Display Value, Internal Value",
        "address,name,display,internal",
    ],
)
def test_only_a_documented_header_row_is_a_header(tmp_path: Path, header: str) -> None:
    path = write(tmp_path, "h.csv", f"{header}\r\n20480,SPEED_AY_0,900,\r\n")
    assert files.read(path) == [ParamValue(0x5000, 0x00400009)]
    later = write(tmp_path, "l.csv", f"20480,SPEED_AY_0,900,\r\n{header}\r\n")
    with pytest.raises(ParamFileError, match=r"l.csv:2: '.*' is no address"):
        files.read(later)


@pytest.mark.parametrize(
    ("name", "text", "message"),
    [
        ("d.yaml", "parameters:\n  - {address: 0x5000, value: .nan}\n", r"d.yaml:1: .*not finite"),
        ("d.json", '{"parameters": [{"address": "0x5000", "value": NaN}]}', r"d.json:1: .*finite"),
        ("d.json", '{"parameters": [{"address": "0x5000", "value": 1e999}]}', "not finite"),
        ("d.json", '{"parameters": [{"address": 20480, "word": 4294967297}]}', "beyond 32"),
        ("d.json", '{"parameters": [{"address": 20480, "word": true}]}', "word is a bool"),
        ("d.yaml", "parameters:\n  - {address: 0x5000, value: 800, wrod: 1}\n", "key.*'wrod'"),
        (
            "d.yaml",
            "parameters:\n  - {address: '0x5000', value: '800'}\n  - {address: 20480, value: 900}\n",
            r"d.yaml:2: 0x5000 SPEED_AY_0 is also on row 1",
        ),
        ("d.yaml", "parameters:\n  - address: [1, 2]\n    value: 1\n", "address is a list"),
        ("d.yaml", "parameters:\n  - 5\n", r"d.yaml:1: each parameter is a mapping, not 5"),
        ("d.yaml", "parameters: 5\n", "expected a 'parameters:' list"),
        ("d.yaml", "parameters: [\n", r"d.yaml: while parsing"),
        ("d.json", "{", r"d.json: Expecting"),
    ],
)
def test_yaml_and_json_entries_follow_the_same_rules(
    tmp_path: Path, name: str, text: str, message: str
) -> None:
    with pytest.raises(ParamFileError, match=message):
        files.read(write(tmp_path, name, text))


def test_an_alias_bomb_is_refused_without_expanding_it(tmp_path: Path) -> None:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 7)]
    path = write(tmp_path, "bomb.yaml", "\n".join([*lines, "parameters:", "  - {address: *a6}"]))
    with pytest.raises(ParamFileError, match=r"bomb.yaml:1: address is a list"):
        files.read(path)


# ------------------------------------------------------------ the bounds


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("deep.json", "[" * 200_000 + "]" * 200_000),
        ("deep.json", '{"a":' * 100_000 + "1" + "}" * 100_000),
        ("deep.yaml", "[" * 200_000 + "]" * 200_000),
        ("deep.yaml", "- " * 200_000 + "1\n"),  # block nesting, no bracket at all
        ("deep.yaml", "".join(f"{' ' * i}a:\n" for i in range(1000)) + " " * 1000 + "1\n"),
    ],
)
def test_deep_nesting_is_one_line_not_a_recursion_error(
    tmp_path: Path, name: str, text: str
) -> None:
    path = write(tmp_path, name, text)
    with pytest.raises(ParamFileError, match=rf"^{path}: nested more than 8 levels deep"):
        files.read(path)


def test_json_brackets_inside_strings_do_not_count(tmp_path: Path) -> None:
    text = '{"parameters": [{"address": "0x5000", "name": "[[[[[[[[[[\\"{{{{{{{{{{", "value": 1}]}'
    assert files.read(write(tmp_path, "s.json", text)) == [ParamValue(0x5000, 1)]


def test_size_and_row_limits(tmp_path: Path) -> None:
    big = write(tmp_path, "big.csv", "20480,SPEED_AY_0,800,4194312\r\n" * 40_000)  # 1.2 MB
    with pytest.raises(ParamFileError, match=rf"^{big}: larger than 1 MiB: not a parameter set"):
        files.read(big)
    rows = "".join(f"{a},,1,\r\n" for a in range(MAX_ROWS + 1))  # distinct addresses
    many = write(tmp_path, "many.csv", rows)
    with pytest.raises(ParamFileError, match=rf"^{many}: more than {MAX_ROWS} parameters"):
        files.read(many)
    assert len(files.read(write(tmp_path, "enough.csv", rows[: rows.rindex(f"{MAX_ROWS},")]))) == (
        MAX_ROWS
    )
    entries = ",".join(f'{{"address": {a}, "value": 1}}' for a in range(MAX_ROWS + 1))
    with pytest.raises(ParamFileError, match=rf"more than {MAX_ROWS} parameters"):
        files.read(write(tmp_path, "many.json", f'{{"parameters": [{entries}]}}'))
    yaml_rows = "".join(f"  - {{address: {a}, value: 1}}\n" for a in range(MAX_ROWS * 3))
    with pytest.raises(ParamFileError, match=rf"more than {MAX_ROWS} parameters"):
        files.read(write(tmp_path, "many.yaml", f"parameters:\n{yaml_rows}"))
    (tmp_path / "dir.csv").mkdir()
    with pytest.raises(ParamFileError, match=r"dir.csv: cannot read: Is a directory"):
        files.read(tmp_path / "dir.csv")  # one line too


def test_a_full_dump_is_well_within_the_bounds(tmp_path: Path) -> None:
    values = [ParamValue(e.address, table.to_word(e.default, e.kind)) for e in table.PARAMETERS]
    for name in ("all.csv", "all.yaml", "all.json"):
        files.write(tmp_path / name, values, "left")
        size = (tmp_path / name).stat().st_size
        assert size < files.MAX_BYTES / 50, size
        assert files.read(tmp_path / name, allow_unknown=False) == values


# ------------------------------------------------------------ set's values


@pytest.mark.parametrize(
    ("value", "kind", "message"),
    [
        (math.nan, "pf", "NaN and infinities are refused"),
        (math.inf, "pf", "NaN and infinities are refused"),
        (-math.inf, "pf", "NaN and infinities are refused"),
        (1e80, "pf", "beyond the packed-float range"),
        (1.5e-72, "pf", "beyond the packed-float range"),
        (1e300, "pf", "beyond the packed-float range"),
        (4294967297.0, "int", "is not a 32-bit integer"),
        (-99999999999.0, "int", "is not a 32-bit integer"),
        (math.nan, "int", "is not a 32-bit integer"),
    ],
)
def test_to_word_refuses_what_the_word_cannot_mean(value: float, kind: str, message: str) -> None:
    with pytest.raises(CodecError, match=message):
        table.to_word(value, kind)  # type: ignore[arg-type]


def test_to_word_keeps_every_value_it_accepts() -> None:
    for value in (800.0, -50.0, 0.1, 0.25, 1e-72, 9.99999e75, -99999999999.0, 4294967297.0):
        back = table.to_value(table.to_word(value, "pf"), "pf")
        assert back == pytest.approx(value, rel=5e-6)
    assert table.to_word(4294967295, "int") == table.to_word(-1, "int") == 0xFFFFFFFF


# ------------------------------------------------------------ end to end: nothing written

SERVICE = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 1{role}}}
"""
# the service only hosts the simulated drive: a monitor, which commands nothing — beside a
# supervisor commanding the drive, `param -c` refuses the bus (docs/safety.md)
HOSTING, TOOL = ", role: monitor", ""


@pytest.mark.wallclock
def test_a_refused_file_or_value_writes_nothing_to_the_drive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every bad file above through `restore --yes` (and `diff`), and `set` with NaN, inf
    and out-of-range values: exit 2, one line naming the mistake, and the simulated drive
    hears no request at all (nothing read, nothing written)."""
    service = parse_config(
        SERVICE.format(channel="pf-nothing", simulate="true", role=HOSTING), "s.yaml"
    )
    tool = tmp_path / "tool.yaml"
    tool.write_text(SERVICE.format(channel="pf-nothing", simulate="false", role=TOOL))
    bad = [write(tmp_path, f"bad{i}.csv", text) for i, (text, _) in enumerate(BAD_ROWS)]
    bad.append(write(tmp_path, "deep.json", "[" * 200_000 + "]" * 200_000))
    bad.append(write(tmp_path, "deep.yaml", "[" * 200_000 + "]" * 200_000))
    bad.append(write(tmp_path, "huge.csv", "20480,SPEED_AY_0,800,4194312\r\n" * 40_000))
    sets = [
        ["SPEED_AY_0", "nan"],
        ["SPEED_AY_0", "inf"],
        ["SPEED_AY_0", "1e999"],
        ["SPEED_AY_0", "1e80"],
        ["CAN_CONTROL_FLAG_LOGIC", "4294967297"],
        ["CAN_CONTROL_FLAG_LOGIC", "-99999999999"],
    ]

    force = {"restore": ["--yes", "--force"], "set": ["--yes", "--force"], "diff": []}

    def cli(*argv: str) -> int:
        return main(["param", "-c", str(tool), *argv])

    async def scenario() -> tuple[list[int], int]:
        async with Runtime(service) as rt:
            await started(rt)  # its start-up check of the drives is done (core/verify.py)
            drive = rt.sims["b"].drives[1]
            before, asked = dict(drive.tel.params), len(drive.tel.requests)
            codes = []
            for path in bad:
                for op in ("restore", "diff"):
                    codes.append(await asyncio.to_thread(cli, op, "left", str(path), *force[op]))
            for address, value in sets:
                codes.append(
                    await asyncio.to_thread(cli, "set", "left", address, value, *force["set"])
                )
            assert drive.tel.params == before
            return codes, len(drive.tel.requests) - asked

    codes, requests = asyncio.run(scenario())
    err = capsys.readouterr().err.splitlines()
    assert codes == [2] * len(codes)
    assert requests == 0  # not even a read: the file is checked before the drive is asked
    assert len(err) == len(codes) and all(line.startswith("error: ") for line in err)
    assert "bad0.csv:1: 0x5000 SPEED_AY_0: internal value '4294967297' is beyond 32 bits" in err[0]
    assert err[-6] == "error: nan is not a finite number: NaN and infinities are refused"
    assert "is not a 32-bit integer" in err[-1]


@pytest.mark.wallclock
def test_restore_with_allow_unknown_writes_exactly_the_files_values(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The maker's header, names and units; an address the table does not have (the
    simulated drive NAKs it: exit 1 after the known one is written)."""
    service = parse_config(
        SERVICE.format(channel="pf-maker", simulate="true", role=HOSTING), "s.yaml"
    )
    tool = tmp_path / "tool.yaml"
    tool.write_text(SERVICE.format(channel="pf-maker", simulate="false", role=TOOL))
    maker = write(
        tmp_path,
        "maker.csv",
        f"{MAKER_HEADER}\r\n"
        '20480,"A,Y 軸 速度制限 #0 [min^-1]","300 [min^-1]",4194307\r\n'
        '16663,"指令ゼロ タイムアウト時間","500 [ms]",500\r\n',
    )
    unknown = write(tmp_path, "unknown.csv", "20480,SPEED_AY_0,800,\r\n30583,0x7777,5,5\r\n")

    def cli(*argv: str) -> int:
        return main(["param", "-c", str(tool), *argv])

    async def scenario() -> list[int]:
        async with Runtime(service) as rt:
            await started(rt)  # its start-up check of the drives is done (core/verify.py)
            drive = rt.sims["b"].drives[1]
            codes = [await asyncio.to_thread(cli, "restore", "left", str(maker), "--yes")]
            assert drive.tel.params[0x5000] == 4194307  # 300
            assert drive.tel.params[0x4117] == 500  # the maker's word, as it is
            codes.append(await asyncio.to_thread(cli, "diff", "left", str(unknown)))
            codes.append(
                await asyncio.to_thread(cli, "diff", "left", str(unknown), "--allow-unknown")
            )
            return codes

    assert asyncio.run(scenario()) == [0, 2, 1]
    captured = capsys.readouterr()
    assert "2 parameter(s) of left restored" in captured.out
    assert "unknown.csv:2: 0x7777 0x7777: not in the parameter table" in captured.err
    assert "0x7777: the drive refused it (NAK)" in captured.err


def test_reading_a_bad_file_is_quick(tmp_path: Path) -> None:
    """A 10⁶-row file, deep nesting: refused at once, not after minutes (generous bound:
    the refusals above read at most 1 MiB and a few thousand events)."""
    start = time.process_time()
    for name, text in [
        ("rows.csv", "20480,SPEED_AY_0,800,4194312\r\n" * 1_000_000),
        ("deep.yaml", "[" * 200_000 + "]" * 200_000),
    ]:
        with pytest.raises(ParamFileError):
            files.read(write(tmp_path, name, text))
    assert time.process_time() - start < 5.0


def test_a_name_neither_table_has_is_refused_with_an_example_of_its_own_kind() -> None:
    """The monitor table's example is a monitor (a drive NAKs 0x5000 as one)."""
    with pytest.raises(CodecError, match=r"is no parameter name or address \(e.g. 0x5000\)"):
        table.parse_address("SPEED_AY_9")
    with pytest.raises(CodecError) as told:
        table.parse_address("SPEED_AY_0", monitor=True)
    assert str(told.value) == (
        "'SPEED_AY_0' is no monitor name or address (e.g. MAIN_VOLTAGE or 0x1004)"
    )
    assert table.parse_address("MAIN_VOLTAGE", monitor=True) == 0x1004
