from torchbrdf.bench.report import machine_description, write_report


def test_the_report_states_the_day_it_ran(tmp_path):
    machine = machine_description()
    machine["load_end"] = machine["load_start"]
    write_report({"machine": machine}, str(tmp_path), ["--out", str(tmp_path)])
    text = (tmp_path / "benchmarks.md").read_text()
    line = next(x for x in text.splitlines() if x.startswith("Machine: "))
    assert len(machine["date"]) == 10 and f", {machine['date']}. Load average" in line
