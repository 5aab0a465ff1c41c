"""Results store and HTML report on hand-written run directories (no GPU, no driver)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from lsbench import cli
from lsbench.report import charts, format, page as report
from lsbench.results import store
from lsbench.running import environment

CHROMIUM = "/usr/bin/chromium"


def fake_record(scene="sponza", structure="grid", backend="glsl", resolution="64", ls_n=0,
                trace=0.010, repeats=5, agreement=1.0, status="ok", reason="", memory=1 << 20,
                rng=None, heatmaps=None, device=None, rays="primary"):
    rng = rng or np.random.default_rng(0)
    ray_count = 128 * 96
    times = list(trace * (1 + 0.02 * rng.standard_normal(repeats))) if status == "ok" else []
    key = f"{scene}|{rays}|{structure}|{backend}|{resolution}|N{ls_n}"
    rec = {
        "key": key, "scene": f"/data/{scene}.ply", "scene_hash": "abc", "triangles": 1000,
        "structure": structure, "backend": backend, "resolution": str(resolution), "ls_n": ls_n,
        "ls_min_candidates": 4 if ls_n else 0, "rays": rays, "ray_count": ray_count,
        "width": 128, "height": 96, "status": status, "reason": reason,
        "device": device or ("llvmpipe (LLVM 15.0.6, 256 bits)" if backend == "glsl" else "pthread-cpu"),
        "driver": "Mesa 22.3.6" if backend == "glsl" else "PoCL 3.1", "backend_version": "x",
        "commit": "0123456789abcdef", "dirty": False, "clock": "perf_counter",
        "heatmaps": heatmaps or {}, "stats": {"iterations_mean": 12.5}, "buffers": {},
        "query": "any" if rays in ("shadow", "ao") else "closest", "ray_params": {},
    }
    if status == "ok":
        n_agree = int(round(agreement * ray_count))
        med = float(np.median(times))
        rec.update({
            "agreement": n_agree / ray_count, "agree": n_agree - 3, "ties": 3,
            "missed": ray_count - n_agree, "extra": 0, "wrong": 0, "max_abs_dt": 1e-6,
            "median_abs_dt": 0.0, "build_seconds": 0.05 * int(str(resolution).split("x")[0]) / 32,
            "trace_seconds": med, "trace_seconds_all": times, "trace_seconds_min": min(times),
            "trace_seconds_max": max(times), "trace_cv": float(np.std(times) / np.mean(times)),
            "rays_per_second": ray_count / med, "fps": 1.0 / med if rays == "primary" else None,
            "memory_bytes": memory, "embree_rays_per_second": ray_count / (EMBREE_SHARE * med),
            "buffers": {"voxels": {"allocated": memory, "used": memory * 3 // 4},
                        "lists": {"allocated": memory // 4, "used": memory // 4}},
        })
    else:
        rec.update({"agreement": None, "agree": None, "ties": None, "missed": None, "extra": None,
                    "wrong": None, "max_abs_dt": None, "median_abs_dt": None,
                    "build_seconds": None, "trace_seconds": None, "trace_seconds_all": [],
                    "trace_seconds_min": None, "trace_seconds_max": None, "trace_cv": None,
                    "rays_per_second": None, "fps": None, "memory_bytes": None})
    return rec


EMBREE_SHARE = 0.5  # Embree takes half the time of every fake case: ×E 0.5 everywhere


FAIL_REASON = "DeviceLimitError: Line Space needs 5.1 GiB > max allocation 1 GiB"


def make_run(run_dir: Path, with_heatmap=True) -> list[dict]:
    rng = np.random.default_rng(1)
    run_dir.mkdir(parents=True, exist_ok=True)
    hm = {}
    if with_heatmap:
        import matplotlib.image
        (run_dir / "heatmaps").mkdir()
        img = np.linspace(0, 1, 64 * 48).reshape(48, 64)
        matplotlib.image.imsave(run_dir / "heatmaps" / "sponza_grid_64_iterations.png", img,
                                cmap="inferno")
        hm = {"iterations": "heatmaps/sponza_grid_64_iterations.png"}
    records = []
    speed = {"grid": 1.0, "svo": 0.7, "esvo": 0.8, "grid-ls": 0.5, "svo-ls": 0.6, "esvo-ls": 0.55}
    for scene in ("sponza", "bmw_m6"):
        for backend in ("glsl", "opencl"):
            for s in ("grid", "svo", "esvo"):
                for res in (32, 64, 128):
                    records.append(fake_record(
                        scene, s, backend, res, trace=0.01 * speed[s] * (1 + abs(res - 64) / 64),
                        memory=int(res ** 3 * 4 * (1 + 0.5 * (s == "svo"))), rng=rng,
                        agreement=1.0 if s != "esvo" else 0.9995,
                        heatmaps=hm if (scene, s, res, backend) == ("sponza", "grid", 64, "glsl") else None))
            for s in ("grid-ls", "svo-ls", "esvo-ls"):
                for n in (1, 2):
                    for res in (32, 64):
                        if (s, n, res) == ("grid-ls", 2, 64):
                            records.append(fake_record(scene, s, backend, res, ls_n=n,
                                                       status="failed", reason=FAIL_REASON))
                            continue
                        records.append(fake_record(scene, s, backend, res, ls_n=n, rng=rng,
                                                   trace=0.004 * speed[s] * n, memory=int(15 * n ** 4 * res ** 3 / 8),
                                                   agreement=1 - 1e-4 * n))
    info = environment.environment_info()
    info.update({"commit": "0123456789abcdef", "dirty": True,
                 "devices": {"glsl": {"device": "llvmpipe (LLVM 15.0.6, 256 bits)", "driver": "Mesa 22.3.6"},
                             "opencl": {"device": "pthread-cpu", "driver": "PoCL 3.1"}},
                 "scenario": {"name": "fake", "path": "scenarios/fake.toml"},
                 "command": "lsbench run scenarios/fake.toml"})
    store.write_run_info(run_dir, info)
    for r in records:
        store.append_record(run_dir, r)
    return records


def test_read_run_tolerates_truncated_last_line(tmp_path):
    recs = make_run(tmp_path / "run", with_heatmap=False)
    path = tmp_path / "run" / "results.jsonl"
    with open(path, "a") as f:
        f.write('{"key": "half-written", "status": "o')  # killed mid-write
    with pytest.warns(UserWarning, match="truncated"):
        info, got = store.read_run(tmp_path / "run")
    assert len(got) == len(recs)
    assert info["scenario"]["name"] == "fake"
    assert {r["key"] for r in got} == {r["key"] for r in recs}


def test_read_run_later_record_of_a_key_wins(tmp_path):
    d = tmp_path / "run"
    store.append_record(d, fake_record(status="failed", reason="timeout"))
    store.append_record(d, fake_record())
    info, recs = store.read_run(d)
    assert info == {} and len(recs) == 1 and recs[0]["status"] == "ok"


def test_git_state_and_environment(tmp_path):
    commit, dirty = environment.git_state(Path(__file__).parent)
    assert commit is None or len(commit) == 40
    assert environment.git_state(tmp_path) == (None, None)
    env = environment.environment_info()
    assert env["versions"]["numpy"] == np.__version__
    assert "T" in env["date"] and env["python"]


def test_list_runs(tmp_path, capsys):
    make_run(tmp_path / "reports" / "a", with_heatmap=False)
    store.append_record(tmp_path / "reports" / "cmp" / "b-HEAD", fake_record(status="failed", reason="x"))
    runs = store.list_runs(tmp_path / "reports")
    assert [Path(r["dir"]).name for r in runs] == ["b-HEAD", "a"]  # undated first
    a = runs[1]
    assert a["ok"] == len(store.read_run(a["dir"])[1]) - 4 and a["failed"] == 4
    assert cli.main(["runs", str(tmp_path / "reports")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 2 and "0123456789+dirty" in out[1] and "ok=80 failed=4" in out[1]


def test_pareto_front():
    pts = [(0.0, 1.0), (0.0, 2.0), (0.1, 3.0), (0.2, 2.5), (0.3, 5.0)]
    assert charts.pareto_front(pts) == [1, 2, 4]


@pytest.fixture(scope="module")
def written_report(tmp_path_factory):
    run = tmp_path_factory.mktemp("rep") / "run"
    records = make_run(run)
    index = report.write_report(run)
    return run, index, records


def test_report_tables_and_failed_reason(written_report):
    run, index, records = written_report
    assert index == run / "index.html"
    page = index.read_text()
    for title in ("Table 1", "Table 2", "Table 3", "Speed against accuracy", "Build time",
                  "Spread of the timing repeats", "Heatmaps", "All cases"):
        assert title in page
    assert "class='fail'" in page and "Line Space needs 5.1 GiB" in page
    assert "llvmpipe" in page and "pthread-cpu" in page
    assert "0123456789+dirty" in page
    assert "http://" not in page and "https://" not in page and "<script" not in page
    # Table 3 has N rows
    t3 = page[page.index("id='table3'"):page.index("id='speed'")]
    assert "N=1" in t3 and "N=2" in t3 and "grid-ls" in t3 and "failed: DeviceLimitError" in t3


def test_report_charts_exist(written_report):
    run, index, _ = written_report
    page = index.read_text()
    charts = sorted((run / "charts").glob("*.png"))
    kinds = {p.name.split("_")[0] for p in charts}
    assert kinds == {"speed", "rays", "build", "repeats", "workload1-primary"}
    assert len(charts) == 9  # 2 scenes x 4 charts + the one workload's
    import matplotlib.image
    for p in charts:
        assert p.stat().st_size > 5000
        assert f"href='charts/{p.name}'" in page  # the PNG is linked, the SVG shown
        svg = p.with_suffix(".svg")
        assert f"src='charts/{svg.name}'" in page and svg.read_text().lstrip().startswith("<?xml")
        assert "<svg" in svg.read_text()
        img = matplotlib.image.imread(p)
        assert img.shape[0] > 200 and img.shape[1] > 400 and img[..., :3].std() > 0.05
    assert "heatmaps/sponza_grid_64_iterations.png" in page
    # every case agrees in some groups: the speed-accuracy chart says so in words (SVG text)
    svg = (run / "charts" / "speed_accuracy_sponza-primary_closest_hit.svg").read_text()
    assert "agree with Embree on every ray" not in svg  # esvo at 0.9995 disagrees
    assert "rays that disagree with Embree per million" in svg


def test_report_out_dir_copies_heatmaps(written_report, tmp_path):
    run, _, _ = written_report
    index = report.write_report(run, tmp_path / "elsewhere")
    page = index.read_text()
    assert index.parent == tmp_path / "elsewhere"
    copied = list((tmp_path / "elsewhere" / "heatmaps").glob("*.png"))
    assert len(copied) == 1 and f"heatmaps/{copied[0].name}" in page


def test_report_of_all_failed_run(tmp_path):
    d = tmp_path / "failed"
    store.append_record(d, fake_record(status="failed", reason="worker crashed: SIGSEGV"))
    page = report.write_report(d).read_text()
    assert "SIGSEGV" in page and "No successful case to plot" in page


def test_report_of_empty_or_missing_folder_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "no-records").mkdir()
    store.write_run_info(tmp_path / "no-records", {"commit": "c" * 40})  # run died before any case
    (tmp_path / "no-records" / "results.jsonl").write_text("")
    for name, why in (("empty", "no results.jsonl"), ("no-records", "results.jsonl is empty"),
                      ("missing", "no run directory")):
        assert cli.main(["report", str(tmp_path / name)]) == 2
        captured = capsys.readouterr()
        assert captured.out == "" and why in captured.err
        assert captured.err.startswith("lsbench report: error: ") and captured.err.count("\n") == 1
        assert not (tmp_path / name / "index.html").exists()


def test_report_reads_min_agreement_from_run_settings(tmp_path):
    d = tmp_path / "run"
    store.write_run_info(d, {"commit": "c" * 40, "settings": {"min_agreement": 0.99}})
    store.append_record(d, fake_record(agreement=0.995))
    assert report.min_agreement(store.read_run(d)[0]) == 0.99
    page = report.write_report(d).read_text()
    assert "agreement with Embree below 0.99." in page
    t1 = page[page.index("id='table1'"):page.index("id='table2'")]
    assert "agree 99.5" in t1 and "class='warn'" not in t1  # 0.995 passes a 0.99 threshold
    # a run that states no rate threshold (zero unexplained disagreements) marks nothing amber
    assert report.min_agreement({"settings": {"min_agreement": None}}) is None
    # folders written before run.json held the settings keep the old default
    assert report.min_agreement({"commit": "c" * 40}) == 0.9999
    assert report.min_agreement({"run": {"min_agreement": 0.9}}) == 0.9


def test_report_cli(written_report, tmp_path, capsys):
    run, _, _ = written_report
    assert cli.main(["report", str(run), "--out", str(tmp_path / "o")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "o" / "index.html")


def test_format_one_slug_and_one_text_table():
    assert format.slug("sponza|primary|grid|glsl|64|N0") == "sponza_primary_grid_glsl_64_N0"
    assert format.slug("/data/a b.ply", "primary") == "data_a_b.ply-primary"
    assert format.slug("|||") == "x" and format.slug("", empty="case") == "case"
    lines = format.text_table(["name", "rays/s", "notes"],
                              [["grid", "1.2 M", ""], ["a-very-long-structure-name", "950", "faster"]],
                              right={1}, max_width={0: 8})
    assert lines == ["name      rays/s  notes",
                     "--------  ------  ------",
                     "grid       1.2 M",
                     "a-very-…     950  faster"]
    assert format.fmt_si(1.234e6, "rays/s") == "1.23 Mrays/s" and format.fmt_si(None) == "-"
    assert format.fmt_mib(3 * 2 ** 20) == "3" and format.fmt_pct(0.9995) == "99.95%"
    assert format.fmt_pct(0.99995) == "99.995%" and format.fmt_pct(1.0) == "100%"


@pytest.mark.skipif(not Path(CHROMIUM).exists(),
                    reason=f"{CHROMIUM} absent (apt-get install -y chromium) — page not rendered")
def test_report_renders_in_headless_chromium(written_report, tmp_path):
    _, index, _ = written_report
    shot = tmp_path / "shot.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run",
           f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
           "--window-size=1280,2000", index.resolve().as_uri()]
    subprocess.run(cmd, capture_output=True, timeout=120)
    assert shot.exists() and shot.stat().st_size > 10000
    import matplotlib.image
    img = matplotlib.image.imread(shot)[..., :3]
    assert img.shape[:2] == (2000, 1280)
    # not blank: many distinct colours, real contrast (text, red failed cells, tables)
    assert img.std() > 0.05
    assert len(np.unique((img.reshape(-1, 3) * 255).astype(np.uint8), axis=0)) > 50
    # the DOM Chromium built: the tables, the SVG charts, the export links, the sections in order
    dom = subprocess.run(cmd[:-3] + ["--dump-dom", index.resolve().as_uri()], capture_output=True,
                         text=True, timeout=120).stdout
    import re
    charts = sorted((index.parent / "charts").glob("*.svg"))
    assert len(re.findall(r'<img class="chart" src="charts/[^"]+\.svg"', dom)) == len(charts) == 9
    # Workload (2 backends) + Tables 1-3 (2 backends each) + environment/devices + all cases
    assert dom.count('<table class="grid">') == 2 + 6 + 1
    assert len(re.findall(r'<a href="tables/[^"]+\.(csv|tex)">', dom)) == 2 * 8
    assert dom.count("★") >= 12 and dom.count('<tr class="ref">') == 2 * 2  # 2 scenes x 2 backends
    heads = [m.group(1) for m in re.finditer(r"<h2 id=\"([a-z0-9]+)\"", dom)]
    assert heads[0] == "workload1" and heads[-1] == "env"


def test_same_name_scenes_in_two_folders_stay_two_scenes(tmp_path):
    run = tmp_path / "run"
    for folder, trace in (("a", 0.010), ("b", 0.020)):
        rec = fake_record(scene="room", trace=trace)
        rec["scene"], rec["scene_source"] = "room", f"/data/{folder}/room.ply"
        rec["key"] = rec["key"].replace("room", f"/data/{folder}/room.ply")
        store.append_record(run, rec)
    page = report.write_report(run).read_text()
    assert "room (/data/a)" in page and "room (/data/b)" in page


# ---- the researcher's report (issue 18): workloads, marks, exports, links, image accuracy -------
def page_links(page: str) -> list[str]:
    import re

    return re.findall(r"(?:href|src)='([^']+)'", page)


def assert_every_link_resolves(index: Path) -> int:
    """Every href/src of the page: a file beside it, or an id on it. Returns how many."""
    import html
    import re

    page = index.read_text()
    ids = set(re.findall(r"id='([^']+)'", page))
    links = page_links(page)
    for link in links:
        link = html.unescape(link)
        assert "://" not in link, link  # opens from disk, nothing fetched
        if link.startswith("#"):
            assert link[1:] in ids, link
        else:
            assert (index.parent / link).is_file(), link
    return len(links)


def test_every_link_of_the_report_resolves(written_report, tmp_path):
    run, index, _ = written_report
    assert assert_every_link_resolves(index) > 40
    # and when the report is written elsewhere (charts, tables and heatmaps go with it)
    assert assert_every_link_resolves(report.write_report(run, tmp_path / "elsewhere")) > 40


def test_results_come_first_and_the_environment_last(written_report):
    page = written_report[1].read_text()
    order = [page.index(f"id='{a}'") for a in ("workload1", "table1", "memory", "speed", "image",
                                                 "heatmaps", "cases", "env")]
    assert order == sorted(order)


def workload_run(run: Path) -> list[dict]:
    """One scene, two workloads (camera rays and shadow rays), three structures, two resolutions."""
    rng = np.random.default_rng(5)
    recs = []
    speed = {"grid": 1.0, "svo": 1.6, "grid-ls": 0.5}
    for rays in ("primary", "shadow"):
        for s, n in (("grid", 0), ("svo", 0), ("grid-ls", 1)):
            for res in (16, 32):
                trace = 0.01 * speed[s] * (1.5 if rays == "shadow" else 1.0) * (1 + res / 64)
                recs.append(fake_record("cornell", s, "opencl", res, ls_n=n, trace=trace, rng=rng, rays=rays,
                                        memory=int(res ** 3 * (40 if n else 4))))
    for r in recs:
        store.append_record(run, r)
    return recs


def test_workload_sections_with_embree_row_best_mark_and_speedups(tmp_path):
    from lsbench.report import tables

    run = tmp_path / "run"
    recs = workload_run(run)
    page = report.write_report(run).read_text()
    heads = [page.index("Workload: primary, closest hit"), page.index("Workload: shadow, any hit")]
    assert heads == sorted(heads)  # the camera workload first
    baselines = tables.Baselines(recs)
    for rays in ("primary", "shadow"):
        mine = [r for r in recs if r["rays"] == rays]
        (table,) = tables.workload_tables(mine, baselines, None, f"w-{rays}")
        assert table.columns == ["grid", "svo", "grid-ls N=1 K>4"]
        data = [row for row in table.rows if not row.reference]
        (ref,) = [row for row in table.rows if row.reference]
        assert ref.labels[1] == "Embree (CPU)" and table.rows[-1] is ref  # below the scene's rows
        embree = sorted(r["embree_rays_per_second"] for r in mine)
        assert len(embree) == 6 and ref.cells[0].value == pytest.approx((embree[2] + embree[3]) / 2)  # median
        for row in data:
            res = row.labels[1].rstrip("³")
            by_col = {c: next(r for r in mine if tables.structure_column(r) == c and r["resolution"] == res)
                      for c in table.columns}
            fastest = max(by_col, key=lambda c: by_col[c]["rays_per_second"])
            assert [c.best for c in row.cells] == [c == fastest for c in table.columns]
            grid = by_col["grid"]["rays_per_second"]
            for col, cell in zip(table.columns, row.cells):
                r = by_col[col]
                assert cell.value == r["rays_per_second"]
                assert f"×E {r['rays_per_second'] / r['embree_rays_per_second']:.3g}" in cell.lines[-1]
                if col != "grid":
                    assert f"×grid {r['rays_per_second'] / grid:.3g}" in cell.lines[-1]
        assert "★" in page and "Embree (CPU)" in page
    # Tables 1 and 3 hold the camera rays only; Table 2 one cell per structure as built
    t1 = page[page.index("id='table1'"):page.index("id='table2'")]
    t2 = page[page.index("id='table2'"):page.index("id='table3'")]
    assert "shadow" not in t1 and t2.count("<tr>") == 1 + 2  # header + 16³ and 32³


def test_tables_export_as_csv_and_latex(tmp_path):
    import csv
    import io

    run = tmp_path / "run"
    recs = workload_run(run)
    index = report.write_report(run)
    page = index.read_text()
    links = [link for link in page_links(page) if link.startswith("tables/")]
    assert {Path(link).suffix for link in links} == {".csv", ".tex"}
    assert len(links) == 2 * 5  # 2 workloads + Tables 1, 2, 3, one backend each
    for link in links:
        assert (run / link).is_file()
    rows = list(csv.reader(io.StringIO((run / "tables" / "workload1-primary-opencl.csv").read_text())))
    assert rows[0][:4] == ["scene", "res.", "grid [rays/s]", "grid notes"]
    by_res = {row[1]: row for row in rows[1:]}
    grid32 = next(r for r in recs if (r["rays"], r["structure"], r["resolution"]) == ("primary", "grid", "32"))
    assert float(by_res["32³"][2]) == grid32["rays_per_second"]
    assert float(by_res["Embree (CPU)"][2]) > 0 and "median of 6 timings" in by_res["Embree (CPU)"][3]
    fastest = rows[0].index("grid-ls N=1 K>4 notes")
    assert all(by_res[res][fastest].startswith("best; ") for res in ("16³", "32³"))  # grid-ls is fastest
    tex = (run / "tables" / "workload1-primary-opencl.tex").read_text()
    assert "\\begin{tabular}{llrrr}" in tex and "\\toprule" in tex and "\\bottomrule" in tex
    assert tex.count("\\textbf{") == 2 and "\\multicolumn{3}{c}{" in tex and "grid-ls N=1 K>4" in tex
    assert tex.count(" \\\\") == 1 + 3  # header, 32³, 16³, Embree


def test_compare_page_is_linked_and_sorted_by_severity(tmp_path, capsys):
    base, head = tmp_path / "base", tmp_path / "head"
    recs = workload_run(base)
    slow_key = recs[2]["key"]
    for r in recs:
        r = dict(r)
        if r["key"] == slow_key:  # 3x slower, far outside the repeats' spread
            r["trace_seconds_all"] = [t * 3 for t in r["trace_seconds_all"]]
            r["trace_seconds"] *= 3
            r["trace_seconds_min"] *= 3
            r["trace_seconds_max"] *= 3
            r["rays_per_second"] /= 3
        store.append_record(head, r)
    assert cli.main(["compare", str(base), str(head), "--report"]) == 1
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("cornell|")]
    assert len(rows) == len(recs) and rows[0].startswith(slow_key) and "REGRESSION" in rows[0]  # worst first
    compare_page = (head / "compare.html").read_text()
    assert compare_page.index(slow_key) < min(compare_page.index(r["key"]) for r in recs if r["key"] != slow_key)
    index = report.write_report(head, tmp_path / "elsewhere")
    assert "href='compare.html'" in index.read_text() and (index.parent / "compare.html").is_file()
    assert "compare.html" not in report.write_report(base).read_text()


def test_image_accuracy_shown_with_its_numbers_and_missing_files_named(tmp_path):
    from lsbench.inputs.rays import make_rays
    from lsbench.inputs.scenes import load_scene
    from lsbench.oracle import image, verify
    from lsbench.oracle.embree import embree_closest

    scene = load_scene("cornell")
    rays = make_rays("primary", scene, 24, 16)
    ref, t = embree_closest(scene, rays)
    ref = np.asarray(ref).astype(np.int64)
    mine = ref.copy()
    mine[np.flatnonzero(ref >= 0)[:7]] = -1  # 7 planted misses
    acc = verify.compare(mine, t, ref, t, scene_extent=1.0)
    run = tmp_path / "run"
    fields = image.image_accuracy(scene, rays, mine, t, ref, t, acc, run / "heatmaps", "cornell|grid")
    ok = fake_record("cornell", "grid", "opencl", 16)
    ok.update(fields)
    gone = fake_record("cornell", "svo", "opencl", 16)
    gone.update(image_delta_e_mean=0.0, image_delta_e_max=0.0, image_jnd_pixels=0,
                image_files={"delta_e": "heatmaps/gone_delta_e.png", "pixel_errors": "heatmaps/gone_pixel_errors.png"})
    for r in (ok, gone):
        store.append_record(run, r)
    index = report.write_report(run)
    page = index.read_text()
    section = page[page.index("id='image'"):page.index("id='build'")]
    assert fields["image_jnd_pixels"] == 7 and "7 px &gt; 2.3" in section
    assert f"max {fields['image_delta_e_max']:.3g}" in section
    for rel in fields["image_files"].values():
        assert f"src='{rel}'" in section
    assert "missing: heatmaps/gone_delta_e.png" in section
    assert "ΔE&gt;2.3 px" in page  # the All cases table has the column
    assert_every_link_resolves(index)


def test_heatmap_rows_stand_when_files_are_missing(tmp_path):
    """A heatmap file or EXR gone from the run folder: the row names it, every link still
    resolves (a row at one shared scale needs every case's EXR; without, each case's own PNG)."""
    import matplotlib.image

    run = tmp_path / "run"
    (run / "heatmaps").mkdir(parents=True)
    matplotlib.image.imsave(run / "heatmaps" / "grid_iterations.png", np.eye(8), cmap="inferno")
    have = fake_record("cornell", "grid", "opencl", 16, heatmaps={
        "exr": "heatmaps/grid.exr", "iterations": "heatmaps/grid_iterations.png"})
    gone = fake_record("cornell", "svo", "opencl", 16, heatmaps={"iterations": "heatmaps/svo_iterations.png"})
    for r in (have, gone):
        store.append_record(run, r)
    index = report.write_report(run)
    section = index.read_text().split("id='heatmaps'")[1].split("id='cases'")[0]
    assert "src='heatmaps/grid_iterations.png'" in section
    assert "missing: heatmaps/svo_iterations.png" in section and "own scale" in section
    assert "missing: heatmaps/grid.exr" in section  # under 'more', not a broken link
    assert_every_link_resolves(index)


def test_case_labels_name_a_bvh_by_its_leaf_size_not_a_resolution():
    from lsbench.report.records import case_label

    assert case_label({"structure": "grid", "resolution": "64", "backend": "glsl"}) == "grid 64³ glsl"
    assert case_label({"structure": "svo-ls", "resolution": "32", "ls_n": 2, "backend": "opencl"}) == \
        "svo-ls 32³ N=2 opencl"
    assert case_label({"structure": "bvh", "resolution": "64", "leaf_size": 8, "backend": "opencl"}) == \
        "bvh leaf 8 opencl"
