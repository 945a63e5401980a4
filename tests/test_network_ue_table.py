"""``ue_reports = "table"`` (issue #53, part 4): the radio network's UE reports as one
``network.ues`` table a step hold what the per-UE ``network.ue`` messages hold, field for field
(read back by ``table_rows``), with the paper's per-UE ``communications.throughput`` unchanged;
with beams, the uplink, a load, ``report_cells``, a UE out of coverage and the layout's dropped
UEs; ``caviar-core report`` reads either; a wrong value is named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from caviar_plugins.network.report import summarize, ue_rows
from caviar_plugins.network.ues import table_rows, ue_reports, ue_table
from configs import episode, output
from network_configs import BAND, SITE_A, SITE_B, STAGES, line_movers, mover, radio_network, run_network


def _analysis(ue_reports: str) -> list[str]:
    return ["communications.throughput", "network.ues" if ue_reports == "table" else "network.ue", "network.events",
            "network.cells"]


def _two_sites(ue_reports: str) -> str:
    """Two sites, three UEs (one 40 km away: no cell), SSB beams, the uplink, FTP both ways and
    the strongest cell's RSRP only, 6 steps of 10 ms."""
    return (episode(0.01, STAGES, steps=6, seed=4) + output(analysis=_analysis(ue_reports))
            + line_movers(mover("victim", (180.0, 60.0, 25.0), (220.0, 60.0, 25.0), 20.0),
                          mover("other", (250.0, -120.0, 25.0)), mover("far", (40_000.0, 0.0, 25.0)))
            + radio_network([SITE_A, SITE_B], **BAND, subcarrier_spacing_hz=30e3, tx_power_dbm=46.0, array=[1, 8],
                            beams={"horizontal": 4, "vertical": 1}, uplink={}, report_cells=1,
                            traffic={"downlink": "ftp3", "uplink": "ftp3",
                                     "ftp": {"file_bytes": 20_000.0, "arrival_rate_hz": 50.0}},
                            ue_reports=ue_reports))


def _dropped(ue_reports: str) -> str:
    """A one-ring 38.901 UMa layout's drop (21 cells, 2 UEs a sector) and a moving UE of another
    module among them, Shannon, 2 steps."""
    return (episode(0.01, STAGES, steps=2, seed=5) + output(analysis=_analysis(ue_reports))
            + line_movers(mover("walker", (30.0, 20.0, 1.5), (60.0, 20.0, 1.5), 1.5))
            + radio_network(channel="38.901-uma", link_model="shannon", ue_reports=ue_reports,
                            layout={"rings": 1, "ues_per_sector": 2}))


def _by_step(log) -> tuple[dict[int, list[dict]], dict[int, list[dict]]]:
    """The run's UE reports and throughputs, by step."""
    reports: dict[int, list[dict]] = {}
    for step, r in ue_rows(log):
        reports.setdefault(step, []).append(r)
    thr: dict[int, list[dict]] = {}
    for m in log.decoded("communications.throughput"):
        thr.setdefault(m.step, []).append(m.data)
    return reports, thr


@pytest.mark.parametrize("config", [_two_sites, _dropped], ids=["beams-uplink-load", "layout-drop"])
def test_the_table_holds_what_the_per_ue_reports_hold(tmp_path, config):
    per_ue = run_network(tmp_path, config("per-ue"), "per-ue", "per-ue.toml")
    table = run_network(tmp_path, config("table"), "table", "table.toml")
    assert not list(table.decoded("network.ue")) and not list(per_ue.decoded("network.ues"))
    tables = [m.data for m in table.decoded("network.ues")]
    assert len(tables) == len({m.step for m in per_ue.decoded("network.ue")})  # (one table a step)
    expected, thr_expected = _by_step(per_ue)
    got, thr_got = _by_step(table)
    assert got == expected  # every field of every UE's report, every step
    # (and as text: the same fields in the same order)
    assert [json.dumps(r) for rows in got.values() for r in rows] == \
        [json.dumps(r) for rows in expected.values() for r in rows]
    assert thr_got == thr_expected
    assert all(t.height == len(thr_got[step]) for t, step in zip(tables, sorted(thr_got), strict=True))  # (a row a UE)


def test_the_table_of_a_loaded_network_has_its_fields_as_columns(tmp_path):
    import polars as pl

    log = run_network(tmp_path, _two_sites("table"), "table", "table.toml")
    last = [m.data for m in log.decoded("network.ues")][-1]
    assert isinstance(last, pl.DataFrame) and last["UE_Id"].to_list() == ["victim", "other", "far"]
    assert last.schema["sinr_db"] == pl.Float64 and last.schema["mcs"] == pl.Int64
    assert [f.name for f in last.schema["rsrp_dbm"].fields] == ["A/0", "B/0"]  # (a field a cell)
    far = 2
    # no cell 40 km away: the fields a per-UE report would leave out or null are null
    assert last["serving_cell"].to_list() == ["A/0", "B/0", None]
    assert last["ul_sinr_db"][far] is None and last["ssb_beam"][far] is None and last["sinr_db"][far] is None
    # report_cells = 1: each row's strongest cell, the other null
    rsrp = last["rsrp_dbm"].to_list()
    assert rsrp[0]["B/0"] is None and rsrp[0]["A/0"] > rsrp[far]["A/0" if rsrp[far]["A/0"] is not None else "B/0"] + 40
    assert last["dl_queue_bytes"].null_count() == 0 and last.schema["dl_queue_bytes"] == pl.Int64
    rows = table_rows(last)
    assert set(rows[0]["rsrp_dbm"]) == {"A/0"} and "ul_sinr_db" not in rows[far] and rows[far]["sinr_db"] is None


def test_report_summarizes_a_table_run_as_a_per_ue_run(tmp_path):
    per_ue = summarize(run_network(tmp_path, _two_sites("per-ue"), "a", "a.toml"))
    table = summarize(run_network(tmp_path, _two_sites("table"), "b", "b.toml"))
    assert per_ue == table and per_ue is not None and per_ue["ue_types"]


def test_a_wrong_ue_reports_is_named():
    from caviar._host import check_params
    from caviar.errors import ConfigError
    from caviar_plugins.network.plugin import RadioNetwork

    with pytest.raises(ConfigError, match=r"expected one of \['per-ue', 'table'\], got 'rows'") as e:
        check_params(RadioNetwork, {"ue_reports": "rows", "sites": [SITE_A]})
    assert e.value.key == "params.ue_reports"


def test_the_table_of_ues_without_a_cell_first_and_cells_not_listed_holds_the_reports_nulls():
    """``ue_table`` built directly: UEs without a cell first and between (their serving cell, SINRs
    and loss null), an RSRP with no number and the cells a UE does not list (``report_cells``) null
    in its struct, the rest as ``ue_reports`` gives them, row for row."""
    names, ids, types = ["c0", "c1", "c2"], ["u0", "u1", "u2", "u3"], ["car"] * 4
    serving = np.array([-1, 0, -1, 2])
    sinr, sir, loss = np.array([np.nan, 3.14159, np.nan, -1.5]), np.array([np.nan, 4.0, np.nan, 2.0]), np.full(4, 90.0)
    rsrp = np.array([[-140.0, -150.0, -160.0], [-80.123, -90.0, -100.0], [-np.inf, -145.0, -150.0],
                     [-95.0, -99.0, -70.0]])
    listed = np.array([[0, 1], [0, 1], [1, 2], [0, 2]])
    mbps, position = np.array([0.0, 12.3456789, 0.0, 1.0]), np.zeros((4, 3))
    table = ue_table(names, ids, types, serving, sinr, sir, loss, rsrp, listed, mbps, None, None, None, [], position)
    assert table["serving_cell"].to_list() == [None, "c0", None, "c2"]
    assert table["rsrp_dbm"].to_list()[2] == {"c0": None, "c1": -145.0, "c2": -150.0}
    want = [r for topic, r in ue_reports(names, ids, types, serving, sinr, sir, loss, rsrp, listed, mbps, None,
                                         [{}] * 4, position) if topic == "network.ue"]
    assert table_rows(table) == want
