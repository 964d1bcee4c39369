"""Tag-list import: Kepware's CSV export and the generic form -> device file items; every
refused row named by row, column, value and reason; the output loads back."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import edgemodbus as em
from edgemodbus.cli import main
from edgemodbus.commission.tag_import import KEPWARE_COLUMNS, Refusal, import_tags

HEADER = ",".join(f'"{c}"' for c in KEPWARE_COLUMNS)


def kepware(*rows: str) -> str:
    return "\n".join([HEADER, *rows]) + "\n"


GOOD = kepware(
    '"Flow","400001","Float",1,R/W,100,"None",,,,,,0,0,"m3/h","Flow rate"',
    '"Level","40003","Word",1,RO,1000,"Linear",0,1000,0,100,"Float",0,0,"%","Tank level"',
    '"Run","000017","Boolean",1,R/W,250,,,,,,,,,,',
    '"Alarm","400005.3","Boolean",1,RO,100,,,,,,,,,,',
    '"Temp","300002","Short",1,RO,500,,,,,,,,,"degC",',
    '"Door","100008","Default",1,RO,500,,,,,,,,,,',
    '"Total","400100","DWord",1,RO,500,,,,,,,,,,',
    '"Energy","300100","LBCD",1,RO,500,,,,,,,,,,',
    '"Count","30050","Default",1,RO,500,,,,,,,,,,',
)


def test_kepware_rows_convert() -> None:
    result = import_tags(GOOD)
    assert result.form == "kepware" and result.refused == []
    assert result.items == [
        {"name": "Flow", "address": "hr:0", "deviceDataType": "Float", "readCycle": 100,
         "unit": "m3/h", "description": "Flow rate"},
        {"name": "Level", "address": "hr:2", "deviceDataType": "UInt16", "dataMultiplier": 0.1,
         "convertedDataType": "Float", "readCycle": 1000, "unit": "%",
         "description": "Tank level"},
        {"name": "Run", "address": "coil:16", "deviceDataType": "Boolean", "readCycle": 250},
        {"name": "Alarm", "address": "hr:4.3", "deviceDataType": "Boolean", "readCycle": 100},
        {"name": "Temp", "address": "ir:1", "deviceDataType": "Int16", "readCycle": 500,
         "unit": "degC"},
        {"name": "Door", "address": "di:7", "deviceDataType": "Boolean", "readCycle": 500},
        {"name": "Total", "address": "hr:99", "deviceDataType": "UInt32", "readCycle": 500},
        {"name": "Energy", "address": "ir:99", "deviceDataType": "BCD32", "readCycle": 500},
        {"name": "Count", "address": "ir:49", "deviceDataType": "UInt16", "readCycle": 500},
    ]
    cfg = em.load_device_config(result.device({"slaveId": 3}))
    assert [str(p.address) for p in cfg.parsed_items()] == [
        "hr:0", "hr:2", "coil:16", "hr:4.3", "ir:1", "di:7", "hr:99", "ir:99", "ir:49"]


def test_linear_scaling_with_an_offset_and_clamped_ranges_convert() -> None:
    """Kepware's Linear extrapolates: a multiplier and an offset; with both clamps it is
    a clamped range (docs/engineering-units.md).  The old importer refused both."""
    text = kepware(
        '"Level","400010","Word",1,RO,100,"Linear",4000,20000,0,100,"Float",0,0,,',
        '"Loop","400011","Word",1,RO,100,"Linear",0,27648,4,20,"Float",1,1,"mA",',
    )
    result = import_tags(text)
    assert result.refused == []
    level, loop = result.items
    assert (level["dataMultiplier"], level["offset"]) == (0.00625, -25.0)
    assert {k: loop[k] for k in ("rawMin", "rawMax", "engMin", "engMax", "clamp")} == {
        "rawMin": 0.0, "rawMax": 27648.0, "engMin": 4.0, "engMax": 20.0, "clamp": True}
    assert "dataMultiplier" not in loop
    em.load_device_config(result.device())


def test_generic_form_takes_the_engineering_units_keys() -> None:
    text = ("name,address,type,offset,rawMin,rawMax,engMin,engMax,clamp,scaleFactor\n"
            "t,hr:1,Int16,-40,,,,,,\n"
            "i,hr:2,UInt16,,0,27648,4,20,true,\n"
            "w,hr:3,Int16,,,,,,,w_sf\n"
            "w_sf,hr:4,Int16,,,,,,,\n"
            "v,hr:5,Int16,,,,,,,nope\n"
            "c,hr:6,Int16,,,,,,maybe,\n"
            "s,hr:7,Int16,,1,,,,,\n")
    result = import_tags(text)
    assert [i["name"] for i in result.items] == ["t", "i", "w", "w_sf"]
    assert result.items[0]["offset"] == -40.0 and result.items[1]["clamp"] is True
    assert result.items[2]["scaleFactor"] == "w_sf"
    assert [str(r) for r in result.refused] == [
        "row 6, column 'scaleFactor', value 'nope': no tag of that name in the list (a scale "
        "factor is an Int16 tag of the same device)",
        "row 7, column 'clamp', value 'maybe': must be true or false (1 or 0)",
        "row 8, column 'rawMax', value '': not allowed: rawMin, rawMax, engMin and engMax all "
        "four, or none (missing: rawMax, engMin, engMax)"]
    em.load_device_config(result.device())


def test_negate_value_is_a_negative_multiplier() -> None:
    text = (HEADER + ',"Negate Value"\n'
            '"Out","400001","Short",1,RO,100,"Linear",0,10,0,1,"Float",0,0,,,1\n')
    (item,) = import_tags(text).items
    assert item["dataMultiplier"] == -0.1 and item["convertedDataType"] == "Float"


@pytest.mark.parametrize(
    ("row", "refusal"),
    [
        ('"S","400010","String",1,RO,1000,,,,,,,,,,',
         Refusal(2, "Data Type", "String", "String is not converted")),
        ('"A","400010","Word Array",1,RO,1000,,,,,,,,,,',
         Refusal(2, "Data Type", "Word Array", "arrays are not converted")),
        ('"C","400010","Char",1,RO,1000,,,,,,,,,,',
         Refusal(2, "Data Type", "Char", "Char (an 8-bit value) is not converted")),
        ('"T","400010","Tiny",1,RO,1000,,,,,,,,,,',
         Refusal(2, "Data Type", "Tiny", "unknown Kepware data type (allowed: Default, "
                                         "Boolean, Short, Word, Long, DWord")),
        ('"R","400010","Word",1,RO,fast,,,,,,,,,,',
         Refusal(2, "Scan Rate", "fast", "must be a number")),
        ('"R","400010","Word",1,RO,0,,,,,,,,,,',
         Refusal(2, "Scan Rate", "0", "must be a whole number of milliseconds, 1 or more")),
        ('"O","400010","Word",1,RO,100,"Linear",0,100,10,20,"Float",1,0,,',
         Refusal(2, "Clamp Low", "1", "clamping one end only is not converted")),
        ('"O","400010","Word",1,RO,100,"Linear",0,100,10,10,"Float",0,0,,',
         Refusal(2, "Scaled High", "10", "must differ from Scaled Low")),
        ('"Q","400010","Word",1,RO,100,"Square Root",0,100,0,20,"Float",0,0,,',
         Refusal(2, "Scaling", "Square Root", "only None and Linear scaling are converted")),
        ('"K","400010","Word",1,RO,100,,,,,,,1,0,,',
         Refusal(2, "Clamp Low", "1", "clamping needs Linear scaling (use 0)")),
        ('"B","500001","Word",1,RO,100,,,,,,,,,,',
         Refusal(2, "Address", "500001", "table digit '5' is not a Modbus table")),
        ('"B","465537","Word",1,RO,100,,,,,,,,,,',
         Refusal(2, "Address", "465537", "entity number out of range: holding registers are "
                                         "40001..49999 (5 digits) or 400001..465536")),
        ('"B","40001 L","Word",1,RO,100,,,,,,,,,,',
         Refusal(2, "Address", "40001 L", "entity number '40001 L' is not a decimal number")),
        ('"B","hr:1","Word",1,RO,100,,,,,,,,,,',
         Refusal(2, "Address", "hr:1", "not a Kepware Modbus address")),
        ('"F","000001","Float",1,RO,100,,,,,,,,,,',
         Refusal(2, "Data Type", "Float", "a coil holds one bit: use Boolean")),
        ('"W","465535","Double",1,RO,100,,,,,,,,,,',
         Refusal(2, "Address", "465535", "4 registers from here run past the last address")),
        ('"","400001","Word",1,RO,100,,,,,,,,,,',
         Refusal(2, "Tag Name", "", "a tag needs a name")),
    ],
)
def test_refused_rows_say_where_and_why(row: str, refusal: Refusal) -> None:
    result = import_tags(kepware(row))
    assert result.items == []
    (got,) = result.refused
    assert (got.row, got.column, got.value) == (refusal.row, refusal.column, refusal.value)
    assert got.reason.startswith(refusal.reason), got.reason


def test_every_bad_row_is_reported_with_its_row_number() -> None:
    text = kepware('"A","400001","Word",1,RO,100,,,,,,,,,,',
                   '"B","400002","Strnig",1,RO,100,,,,,,,,,,',
                   "",
                   '"A","400003","Word",1,RO,100,,,,,,,,,,',
                   '"C","400004","Word",1,RO,100,,,,,,,,,,')
    result = import_tags(text)
    assert [i["name"] for i in result.items] == ["A", "C"]
    assert [str(r) for r in result.refused] == [
        "row 3, column 'Data Type', value 'Strnig': unknown Kepware data type (allowed: "
        "Default, Boolean, Short, Word, Long, DWord, LLong, QWord, Float, Double, BCD, LBCD)",
        "row 5, column 'Tag Name', value 'A': duplicate tag name (also row 2)"]


def test_generic_form() -> None:
    text = ("name,address,type,scanRate,scale\n"
            "speed,hr:100,Float,500,\n"
            "temp,ir:3,Int16,,0.1\n"
            "bad,hr:1,Floot,,\n"
            "far,40001,UInt16,,\n")
    result = import_tags(text)
    assert result.form == "generic"
    assert result.items == [
        {"name": "speed", "address": "hr:100", "deviceDataType": "Float", "readCycle": 500},
        {"name": "temp", "address": "ir:3", "deviceDataType": "Int16", "dataMultiplier": 0.1},
        {"name": "far", "address": "hr:40001", "deviceDataType": "UInt16"},
    ]
    assert [(r.row, r.column, r.value) for r in result.refused] == [(4, "type", "Floot")]
    entity = import_tags(text, "entity")
    assert entity.items[-1]["address"] == "hr:0"


def test_unknown_header_is_refused_naming_both_forms() -> None:
    with pytest.raises(ValueError, match=r"not a tag list this importer knows \(Kepware's "
                                         r"export: Tag Name, Address, Data Type"):
        import_tags("tag,register\nx,1\n")


def test_cli_refuses_unless_partial(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "tags.csv"
    src.write_text(kepware('"A","400001","Float",1,RO,100,,,,,,,,,,',
                           '"B","400003","String",1,RO,100,,,,,,,,,,'), encoding="utf-8")
    out = tmp_path / "device.json"
    assert main(["import", str(src), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{src}: row 3, column 'Data Type', value 'String': String is not converted" in err
    assert "1 rows converted, 1 refused" in err and not out.exists()
    assert main(["import", str(src), "-o", str(out), "--partial", "--slave", "7"]) == 0
    cfg = em.load_device_config(out)
    assert cfg.communication.slave_id == 7
    assert [(i.name, i.address) for i in cfg.address_list] == [("A", "hr:0")]


def test_cli_writes_stdout_and_exits_0_when_all_rows_convert(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "tags.csv"
    src.write_text(GOOD, encoding="utf-8-sig")
    assert main(["import", str(src), "--device-code", "Tank7"]) == 0
    device = json.loads(capsys.readouterr().out)
    assert device["organization"] == {"deviceCode": "Tank7"}
    assert len(em.load_device_config(device).address_list) == 9
