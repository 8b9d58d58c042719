"""Simulated stays simulated in every artefact of ``qc history`` (issue 34): a control
chart drawn from simulated records says SIMULATED (title, points, a mark across the
plot), the JSON records carry it, and a history that leaves every record out says so
instead of writing nothing (``--chart``: exit 1) or printing a table of headers only."""

from __future__ import annotations

import json
from dataclasses import replace

from rig.qc.cli import EXIT_NOTHING_CHARTED
from rig.qc.history import control_charts, left_out
from rig.qc.records import CharacteristicRecord, Records
from tests.test_qc_records import qc, record


def simulated_db(tmp_path, simulated=(True, True, True)) -> str:
    url = f"sqlite:///{tmp_path / 'r.sqlite'}"
    records = Records.open(url, create=True)
    for i, (value, sim) in enumerate(zip((5.95, 6.05, 6.00), simulated, strict=True)):
        base = record(f"SN-{i:04d}", f"u{i}")
        c = base.characteristics[0]
        records.add(replace(base, verdict="PASS", simulated=sim, characteristics=(
            CharacteristicRecord(c.name, c.unit, value, c.std, c.std_fit, c.u_cal, c.low, c.high, c.nominal,
                                 "PASS"),)))
    records.close()
    return url


def test_without_include_simulated_nothing_is_written_and_the_line_says_why(tmp_path, capsys):
    url = simulated_db(tmp_path)
    code, out = qc(capsys, "history", "--db", url, "--chart", str(tmp_path / "charts"))
    assert code == EXIT_NOTHING_CHARTED == 1
    assert f"no chart written to {tmp_path / 'charts'}: no unit to chart (3 simulated (measured on the simulator; " \
           "--include-simulated counts them) left out)" in out
    assert not list((tmp_path / "charts").glob("*.png"))
    # the capability table is not headers only: it says why there is nothing to count
    assert "Capability: no unit to count (3 simulated" in out and "│ characteristic" not in out


def test_with_include_simulated_the_chart_says_simulated(tmp_path, capsys, monkeypatch):
    url = simulated_db(tmp_path, (True, False, True))
    titles, marks = [], []
    import matplotlib.axes

    real_text = matplotlib.axes.Axes.text

    def text(self, x, y, s, *args, **kwargs):
        marks.append(s)
        return real_text(self, x, y, s, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "text", text)
    real_title = matplotlib.axes.Axes.set_title

    def title(self, label, *args, **kwargs):
        titles.append(label)
        return real_title(self, label, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "set_title", title)
    code, out = qc(capsys, "history", "--db", url, "--chart", str(tmp_path / "charts"), "--include-simulated")
    assert code == 0 and (tmp_path / "charts" / "gas_precharge_bar.png").is_file()
    assert titles[0].startswith("SIMULATED (2 of 3 units): Individuals chart")
    assert "SIMULATED" in marks


def test_a_chart_of_measured_units_only_carries_no_mark(tmp_path, monkeypatch):
    url = simulated_db(tmp_path, (False, False, False))
    records = Records.open(url)
    found = records.find()
    records.close()
    assert left_out(found) is None
    titles: list[str] = []
    import matplotlib.axes

    real_title = matplotlib.axes.Axes.set_title
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title",
                        lambda self, label, *a, **k: (titles.append(label), real_title(self, label, *a, **k))[1])
    (path,) = control_charts(found, tmp_path / "charts")
    assert titles[0].startswith("Individuals chart") and "SIMULATED" not in titles[0]


def test_the_json_records_carry_the_mark(tmp_path, capsys):
    url = simulated_db(tmp_path, (True, False, True))
    code, out = qc(capsys, "history", "--db", url, "--json")
    assert code == 0 and [d["simulated"] for d in json.loads(out)] == [True, False, True]


def test_spec_limit_labels_lie_inside_the_plot(tmp_path, monkeypatch):
    """'USL 495 N' was cut by the plot's top edge: each spec label now sits on the
    tolerance band's side of its line, and the y range holds every line."""
    import matplotlib.figure
    from matplotlib.text import Annotation

    url = simulated_db(tmp_path, (False, False, False))
    records = Records.open(url)
    found = [replace(r, characteristics=(replace(r.characteristics[0], high=6.05 + 0.0),)) for r in records.find()]
    records.close()
    checked: list[str] = []
    real_savefig = matplotlib.figure.Figure.savefig

    def savefig(fig, *args, **kwargs):
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        for ax in fig.axes:
            box = ax.get_window_extent(renderer)
            for child in ax.get_children():
                if isinstance(child, Annotation) and child.get_text().startswith(("USL", "LSL")):
                    label = child.get_window_extent(renderer)
                    assert box.y0 <= label.y0 and label.y1 <= box.y1, child.get_text()
                    checked.append(child.get_text())
        return real_savefig(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", savefig)
    control_charts(found, tmp_path / "charts")
    assert sorted(checked) == ["LSL 5.7 bar", "USL 6.05 bar"]


def test_a_session_measured_on_a_simulator_says_so_in_its_dataset_file(tmp_path):
    from rig.session.storage import Session

    def create(name: str, peers: dict | None) -> dict:
        Session.create(tmp_path / name, plan_source="standard", letters=["j"], periods=None, date="261126",
                       snapshot={}, unit={"serial": "SN-1"}, endpoints={}, peers=peers)
        return json.loads((tmp_path / name / "dataset.json").read_text())

    simulated = create("sim", {"controller": {}, "daq": "DAQ4,SIM0001,1.00,SIMULATOR", "simulated": True})
    assert simulated["simulated"] is True and "SIMULATED" in simulated["name"]
    measured = create("rig", {"controller": {}, "daq": "DAQ4,A123,1.00", "simulated": False})
    assert "simulated" not in measured and "SIMULATED" not in measured["name"]
