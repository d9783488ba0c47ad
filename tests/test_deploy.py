"""The monitoring stack of deploy/ (issue 12 item 3), checked without a Docker engine.

compose.yaml's `monitoring` profile mounts files that exist where Grafana and Prometheus
look for them; prometheus.yml scrapes the ports the compose header tells config.toml to
set (and promtool accepts it when installed); every metric the dashboard's PromQL uses is
exported by a real daemon and recorder, scraped over HTTP, and every metric they export has
a panel; the dashboard's SQL, expanded as Grafana's PostgreSQL data source expands it, runs
against real stores (SQLite, a real PostgreSQL server, a real CrateDB when
PSEUDOTWIN_TEST_CRATEDB is set) and returns exactly the rows written there.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import shutil
import sqlite3
import subprocess
import sys
import tomllib
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pandas as pd
import promql_parser
import pytest
import yaml

from daemon_support import DAY, HOURS, REF, TARGET, off_grid, wait_for, write_config
from pseudotwin.config import load_config
from pseudotwin.edge.clock import ReplayClock
from pseudotwin.edge.recorder import Recorder
from pseudotwin.edge.service import Service
from pseudotwin.history.store import CrateStore, EstimateRow, SQLiteStore, open_store
from test_daemon import publisher, reading
from test_prometheus import TOPIC, free_port, scrape, with_metrics

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
COMPOSE = DEPLOY / "compose.yaml"
DASHBOARD = DEPLOY / "grafana" / "dashboards" / "pseudotwin.json"
DATASOURCES = DEPLOY / "grafana" / "provisioning" / "datasources" / "pseudotwin.yaml"
PROVIDERS = DEPLOY / "grafana" / "provisioning" / "dashboards" / "pseudotwin.yaml"
PROMETHEUS = DEPLOY / "prometheus.yml"
MONITORING = ("recorder", "prometheus", "grafana")
#: Series Prometheus makes itself for every target; no exporter has them.
SYNTHETIC = {"up"}
STORE_SCHEMA = "pseudotwin"  # the default schema of crate:// and postgresql:// stores
STORE_UID = "pseudotwin-cratedb"
PROM_UID = "pseudotwin-prometheus"


def load_yaml(path: Path) -> Any:
    return yaml.safe_load(path.read_text(encoding="utf-8"))


def compose() -> dict[str, Any]:
    return load_yaml(COMPOSE)


def dashboard() -> dict[str, Any]:
    return json.loads(DASHBOARD.read_text(encoding="utf-8"))


def all_panels(panels: list[dict]) -> Iterator[dict]:
    for p in panels:
        yield p
        yield from all_panels(p.get("panels", []))  # collapsed rows hold their panels


def targets(uid: str) -> list[tuple[dict, dict]]:
    """(panel, target) of every query of the dashboard sent to data source ``uid``."""
    out = []
    for p in all_panels(dashboard()["panels"]):
        for t in p.get("targets", []):
            ds = t.get("datasource") or p.get("datasource") or {}
            if ds.get("uid") == uid:
                out.append((p, t))
    return out


def datasource(kind: str) -> dict[str, Any]:
    (ds,) = [d for d in load_yaml(DATASOURCES)["datasources"] if kind in d["type"]]
    return ds


def bind_mounts(service: dict[str, Any]) -> dict[str, Path]:
    """Container path → host path of the service's bind mounts relative to deploy/."""
    out = {}
    for v in service.get("volumes", []):
        src, dst = v.split(":")[:2]
        if src.startswith("."):
            out[dst] = (DEPLOY / src).resolve()
    return out


def header() -> str:
    return "".join(line for line in COMPOSE.read_text(encoding="utf-8").splitlines(True)
                   if line.startswith("#"))


def documented_metrics() -> dict[str, Any]:
    """The compose header's `[metrics]` line, read as the TOML it stands for."""
    m = re.search(r"^#\s+\[metrics\]\s+(.+)$", header(), re.MULTILINE)
    assert m, "compose.yaml's header must show the [metrics] settings of the stack"
    return tomllib.loads(re.sub(r"\s{2,}", "\n", m.group(1).strip()))


# -- compose, provisioning, prometheus.yml --------------------------------------------------
def test_monitoring_profile_mounts_existing_provisioning_where_grafana_reads_it() -> None:
    services = compose()["services"]
    for name in MONITORING:
        assert services[name].get("profiles") == ["monitoring"], name
    for name in ("mosquitto", "crate", "pseudotwin"):
        assert "profiles" not in services[name], f"{name} must start without a profile"
    for name, svc in services.items():
        for dst, src in bind_mounts(svc).items():
            assert src.exists(), f"{name}: {src} (mounted at {dst}) does not exist"

    grafana = bind_mounts(services["grafana"])
    assert grafana["/etc/grafana/provisioning/datasources"] == DATASOURCES.parent
    assert grafana["/etc/grafana/provisioning/dashboards"] == PROVIDERS.parent
    (provider,) = load_yaml(PROVIDERS)["providers"]
    assert provider["type"] == "file"
    assert (grafana[provider["options"]["path"]] / DASHBOARD.name).is_file()
    env = dict(e.split("=", 1) for e in services["grafana"]["environment"] if "=" in e)
    home = Path(env["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"])
    assert grafana[str(home.parent)] / home.name == DASHBOARD
    assert bind_mounts(services["prometheus"])["/etc/prometheus/prometheus.yml"] == PROMETHEUS
    # Grafana expands $VAR in provisioning values from its own environment
    for var in re.findall(r"\$(\w+)", json.dumps(load_yaml(DATASOURCES))):
        assert var in env or var in services["grafana"]["environment"], var


def test_prometheus_scrapes_the_ports_the_compose_header_documents(tmp_path: Path) -> None:
    metrics = documented_metrics()
    # the header's snippet is a valid [metrics] table of the daemon's configuration
    # (load_config does not open artifacts)
    cfg = load_config(with_metrics(write_config(tmp_path, 1883, tmp_path / "desk.json"),
                                   "".join(f"{k} = {json.dumps(v)}\n"
                                           for k, v in metrics.items())))
    assert cfg.metrics.host == "0.0.0.0"  # reachable from the prometheus container
    expected = {"pseudotwin": cfg.metrics.port, "recorder": cfg.metrics.record_port}

    services = compose()["services"]
    prom = load_yaml(PROMETHEUS)
    scraped = {}
    for job in prom["scrape_configs"]:
        for sd in job["dns_sd_configs"]:
            for name in sd["names"]:
                scraped[name] = sd["port"]
    assert scraped == expected
    for name, port in scraped.items():
        assert str(port) in [str(p) for p in services[name]["expose"]], name
    # the services the data sources name, on the ports their images listen on
    assert datasource("prometheus")["url"] == "http://prometheus:9090"
    assert "prometheus" in services
    assert datasource("postgresql")["url"] == "crate:5432"  # CrateDB's PostgreSQL port
    assert "crate" in services
    assert datasource("prometheus")["jsonData"]["timeInterval"] \
        == prom["global"]["scrape_interval"]


@pytest.mark.skipif(shutil.which("promtool") is None,
                    reason="promtool not installed (Debian package prometheus)")
def test_promtool_accepts_prometheus_yml() -> None:
    res = subprocess.run(["promtool", "check", "config", str(PROMETHEUS)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr


def test_every_dashboard_query_goes_to_a_provisioned_datasource() -> None:
    provisioned = {d["uid"]: d["type"] for d in load_yaml(DATASOURCES)["datasources"]}
    used = {}
    for p in all_panels(dashboard()["panels"]):
        for t in p.get("targets", []):
            ds = t.get("datasource") or p["datasource"]
            used[ds["uid"]] = ds["type"]
            assert ("expr" in t) == (ds["type"] == "prometheus"), p["title"]
            assert ("rawSql" in t) == (ds["type"] == provisioned[STORE_UID]), p["title"]
    for v in dashboard()["templating"]["list"]:
        used[v["datasource"]["uid"]] = v["datasource"]["type"]
    assert used == provisioned


# -- PromQL vs the real endpoints -------------------------------------------------------------
def promql_metric_names() -> set[str]:
    """Every metric name the dashboard's PromQL selects (parsed, not grepped), with the
    Grafana variables replaced by values Prometheus would see."""
    names: set[str] = set()
    exprs = [t["expr"] for _, t in targets(PROM_UID)]
    exprs += [v["definition"] for v in dashboard()["templating"]["list"]
              if v["datasource"]["uid"] == PROM_UID]
    for expr in exprs:
        for variable, value in (("$__rate_interval", "1m"), ("$__range", "6h"),
                                ("$twin", ".*")):
            expr = expr.replace(variable, value)
        assert "$" not in expr, f"unexpanded Grafana variable in {expr!r}"
        m = re.fullmatch(r"label_values\((\w+), *\w+\)", expr)
        if m:  # a variable query: Grafana's function, not PromQL
            names.add(m.group(1))
            continue

        def visit(node: object) -> None:
            if isinstance(node, promql_parser.VectorSelector) and node.name:
                names.add(node.name)

        promql_parser.walk(promql_parser.parse(expr), visit)
    return names


@pytest.fixture
def endpoints(mosquitto, desk_artifact: Path, tmp_path: Path) -> Iterator[tuple[int, int]]:
    """A real daemon and a real recorder with metrics on, each fed one good and one bad
    reading through the broker, so that every labelled series exists: their ports."""
    port, record_port = free_port(), free_port()
    path = with_metrics(
        write_config(tmp_path, mosquitto.port, desk_artifact,
                     store=str(tmp_path / "history.db")),
        f"port = {port}\nrecord_port = {record_port}\n")
    cfg = load_config(path)
    svc = Service(cfg, clock=ReplayClock(off_grid(9.0), 1.0))
    rec = Recorder(cfg)
    svc.start(wait_connected=15)
    try:
        rec.start(wait_connected=15)
        try:
            pub = publisher(mosquitto.port, "deploy-bridge")
            pub.publish(TOPIC, reading(HOURS.at(DAY, 8.5), 21.0), qos=1).wait_for_publish(10)
            pub.publish(TOPIC, b"{broken", qos=1).wait_for_publish(10)
            wait_for(lambda: svc.accepted == 1 and svc.rejections.run_total == 1
                     and rec.written == 1 and rec.rejections.run_total == 1,
                     what="both processes handled both payloads")
            pub.loop_stop()
            yield port, record_port
        finally:
            rec.stop()
    finally:
        svc.stop()


def test_every_metric_of_the_dashboard_is_exported_and_every_export_has_a_panel(
    endpoints: tuple[int, int]
) -> None:
    exported = {name for port in endpoints for name, _ in scrape(port)}
    used = promql_metric_names()
    assert used - SYNTHETIC <= exported, sorted(used - SYNTHETIC - exported)
    # The other way round: a metric added to edge/prometheus.py needs a panel here.
    # Families are matched by name prefix (histogram _bucket/_sum/_count, counter _total).
    families = {re.sub(r"_(total|bucket|sum|count)$", "", n) for n in exported}
    unused = sorted(f for f in families if not any(u.startswith(f) for u in used))
    assert not unused, f"exported but on no panel: {unused}"
    # a histogram's quantiles need its buckets, its mean _sum and _count
    assert {"pseudotwin_update_latency_seconds_bucket", "pseudotwin_update_latency_seconds_sum",
            "pseudotwin_update_latency_seconds_count"} <= used


# -- SQL vs the real stores ------------------------------------------------------------------
FROM = HOURS.at(DAY, 9.0)
TO = HOURS.at(DAY, 11.0)
INTERVAL = "1m"
MINUTES = [HOURS.at(DAY, 10.0 + i / 60) for i in range(5)]
VARIABLES = {"twin": ["desk"], "model": ["corrgp-lcm", "triv"], "band": ["triv"],
             "sensor": [REF, TARGET]}


def grafana_sql(raw: str, *, epoch_ms: bool, schema: str = STORE_SCHEMA) -> str:
    """``raw`` as Grafana's PostgreSQL data source sends it (its macros.go): variables
    quoted and joined, $__interval, then the macros. ``epoch_ms``: the SQLite store, whose
    ts columns are epoch milliseconds instead of timestamptz."""
    def quoted(values: list[str]) -> str:
        return ",".join("'" + v.replace("'", "''") + "'" for v in values)

    sql = raw.replace("$__interval", INTERVAL)
    for name, values in VARIABLES.items():
        sql = re.sub(rf"\${name}\b", quoted(values), sql)
    seconds = pd.Timedelta(INTERVAL).total_seconds()

    def macro(m: re.Match[str]) -> str:
        name, args = m.group(1), [a.strip() for a in m.group(2).split(",")]
        if name == "__timeFilter":
            if epoch_ms:
                return f"{args[0]} BETWEEN {ms(FROM)} AND {ms(TO)}"
            return f"{args[0]} BETWEEN '{rfc3339(FROM)}' AND '{rfc3339(TO)}'"
        if name == "__timeGroupAlias":
            assert pd.Timedelta(args[1]).total_seconds() == seconds
            if epoch_ms:
                return f'({args[0]} / {int(seconds * 1000)}) * {seconds:g} AS "time"'
            return f'floor(extract(epoch from {args[0]})/{seconds:g})*{seconds:g} AS "time"'
        raise AssertionError(f"macro ${name} is not mirrored here: check it on CrateDB")

    sql = re.sub(r"\$([_a-zA-Z0-9]+)\(([^)]*)\)", macro, sql)
    assert "$" not in sql, sql
    return sql.replace(f"{STORE_SCHEMA}.", f"{schema}.")


def ms(t: dt.datetime) -> int:
    return int(t.timestamp() * 1000)


def rfc3339(t: dt.datetime) -> str:
    return t.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def fill(store_url: str) -> None:
    """Readings of both sensors and estimates of two models of twin desk (and one of
    another twin, which no query for desk may return), one a minute, and one finished
    backfill day."""
    store = open_store(store_url)
    try:
        store.write_readings(pd.DataFrame({
            "sensor": [s for s in (REF, TARGET) for _ in MINUTES],
            "ts": pd.DatetimeIndex([t for _ in (REF, TARGET) for t in MINUTES]),
            "value": [20.0 + i / 10 + (s == TARGET) for s in (REF, TARGET)
                      for i in range(len(MINUTES))],
        }))
        store.write_estimates(
            [EstimateRow(twin, model, t, value(model, i, twin), 0.25, "ok", "abc")
             for twin, models in (("desk", ("triv", "corrgp-lcm")), ("other", ("triv", "ref")))
             for model in models for i, t in enumerate(MINUTES)])
        store.mark_day_done("desk@abc", DAY, 10)
    finally:
        store.close()


def value(model: str, i: int, twin: str = "desk") -> float:
    return 21.0 + i / 10 + {"triv": 0.0, "corrgp-lcm": 0.5, "ref": 3.0}[model] + \
        (twin == "other") * 10



def expected(ref: str) -> set[tuple]:
    secs = [t.timestamp() for t in MINUTES]
    if ref == "A":  # estimates of the chosen models of the twin
        return {(s, m, value(m, i)) for m in VARIABLES["model"] for i, s in enumerate(secs)}
    if ref == "B":  # readings of the chosen sensors
        return {(s, sensor, 20.0 + i / 10 + (sensor == TARGET))
                for sensor in VARIABLES["sensor"] for i, s in enumerate(secs)}
    # C: the ±2σ band of the band model
    return {(s, value("triv", i) - 0.5, value("triv", i) + 0.5) for i, s in enumerate(secs)}


def rounded(rows: list) -> set[tuple]:
    return {tuple(round(float(x), 6) if isinstance(x, (int, float)) or _numeric(x) else x
                  for x in r) for r in rows}


def _numeric(x: object) -> bool:
    try:
        float(x)  # type: ignore[arg-type]  # Decimal from PostgreSQL
        return not isinstance(x, str)
    except (TypeError, ValueError):
        return False


def check_queries(run: Callable[[str], list], *, epoch_ms: bool,
                  schema: str = STORE_SCHEMA) -> None:
    """Run every SQL of the dashboard through ``run`` and compare with what fill wrote."""
    checked = set()
    for panel, t in targets(STORE_UID):
        rows = run(grafana_sql(t["rawSql"], epoch_ms=epoch_ms, schema=schema))
        if "backfill_progress" in t["rawSql"]:
            assert [tuple(r[:3]) for r in rows] == [("desk@abc", DAY.isoformat(), 10)]
            checked.add("progress")
            continue
        assert panel.get("repeat") or _row_repeat(panel) == "twin", panel["title"]
        got = rounded(rows)
        assert got == rounded(list(expected(t["refId"]))), (t["refId"], sorted(got))
        checked.add(t["refId"])
    assert checked == {"A", "B", "C", "progress"}
    for v in dashboard()["templating"]["list"]:
        if v["datasource"]["uid"] != STORE_UID:
            continue
        got = [r[0] for r in run(grafana_sql(v["query"], epoch_ms=epoch_ms, schema=schema))]
        want = {"model": ["corrgp-lcm", "ref", "triv"], "band": ["corrgp-lcm", "ref", "triv"],
                "sensor": sorted([REF, TARGET])}[v["name"]]
        assert got == want, v["name"]


def _row_repeat(panel: dict) -> str | None:
    """The repeat variable of the row the panel sits under (rows own what follows them)."""
    current = None
    for p in dashboard()["panels"]:
        if p["type"] == "row":
            current = p.get("repeat")
        elif p["id"] == panel["id"]:
            return current
    return None


#: The SQL vocabulary of the dashboard's queries besides column names (keywords, functions,
#: the ``metric`` alias Grafana names series by): any other word must be a column.
SQL_WORDS = {"select", "from", "where", "and", "in", "as", "group", "by", "order", "desc",
             "limit", "distinct", "avg", "metric"}


def test_sql_matches_the_cratedb_schema_the_compose_stack_runs() -> None:
    """Every table and column the dashboard names is in CrateStore's DDL (and the ts
    columns are timestamptz, which $__timeFilter's quoted RFC 3339 bounds need)."""
    crate: dict[str, set[str]] = {}
    for ddl in CrateStore.DDL:
        m = re.match(r"CREATE TABLE IF NOT EXISTS (\w+) \((.*)\)", ddl)
        assert m, ddl
        crate[m.group(1)] = set(re.findall(r"(?:^|, )(\w+) (?:TEXT|TIMESTAMP|DOUBLE|INTEGER)",
                                           m.group(2)))
    assert {"ts TIMESTAMP WITH TIME ZONE" in d for d in CrateStore.DDL[:2]} == {True}
    sqls = [t["rawSql"] for _, t in targets(STORE_UID)]
    sqls += [v["query"] for v in dashboard()["templating"]["list"]
             if v["datasource"]["uid"] == STORE_UID]
    for sql in sqls:
        (table,) = re.findall(rf"FROM {STORE_SCHEMA}\.(\w+)", sql)
        assert table in crate, sql
        # Neither literals, quoted aliases, the table nor Grafana's $variables and macros.
        bare = re.sub(rf"'[^']*'|\"[^\"]*\"|{STORE_SCHEMA}\.\w+|\$\w+", "", sql)
        words = set(re.findall(r"\b([a-z_]+)\b", bare.lower()))
        columns = {c for tbl in crate.values() for c in tbl}
        assert words & columns <= crate[table], (table, words & columns - crate[table])
        assert words - SQL_WORDS <= crate[table], (table, words - SQL_WORDS - crate[table])
    # The SQLite store (on which test_sql_runs_on_a_real_sqlite_store runs the queries)
    # has the same columns: CrateDB's only extra is its generated partition column.
    db = sqlite3.connect(":memory:")
    for ddl in SQLiteStore.DDL:
        db.execute(ddl)
    for table, cols in crate.items():
        have = {r[1] for r in db.execute(f"PRAGMA table_info({table})")}
        assert cols - {"month"} == have, table


def test_sql_runs_on_a_real_sqlite_store(tmp_path: Path) -> None:
    path = tmp_path / "history.db"
    fill(str(path))
    db = sqlite3.connect(":memory:")
    db.execute("ATTACH DATABASE ? AS pseudotwin", (str(path),))  # the schema name as-is
    try:
        check_queries(lambda sql: db.execute(sql).fetchall(), epoch_ms=True)
    finally:
        db.close()


def test_sql_runs_on_a_real_postgresql_server(postgres) -> None:
    """PostgreSQL has CrateDB's timestamptz columns and wire protocol: the SQL runs exactly
    as Grafana's data source expands it."""
    import psycopg

    name = postgres.create_database()
    try:
        fill(postgres.url(name))
        with psycopg.connect(postgres.url(name)) as conn:
            check_queries(lambda sql: conn.execute(sql).fetchall(), epoch_ms=False)
    finally:
        postgres.drop_database(name)


REAL_CRATEDB = os.environ.get("PSEUDOTWIN_TEST_CRATEDB")


@pytest.mark.skipif(not REAL_CRATEDB, reason="set PSEUDOTWIN_TEST_CRATEDB=crate://host:4200")
def test_sql_runs_on_a_real_cratedb() -> None:
    assert REAL_CRATEDB is not None
    schema = f"pt_test_{uuid.uuid4().hex[:10]}"
    url = f"{REAL_CRATEDB}{'&' if '?' in REAL_CRATEDB else '?'}schema={schema}"
    fill(url)
    store = open_store(url)
    try:
        run = store._run  # type: ignore[attr-defined]
        run("REFRESH TABLE readings, estimates, backfill_progress")  # fill's writes visible
        check_queries(run, epoch_ms=False, schema=schema)
    finally:
        for table in ("readings", "estimates", "backfill_progress", "meta"):
            store._run(f"DROP TABLE IF EXISTS {table}")  # type: ignore[attr-defined]
        store.close()



@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_the_systemd_units_verify_and_wait_for_readiness_however_long(tmp_path: Path) -> None:
    """systemd-analyze checks every directive (the executable pointed at this checkout's, the
    units' own path being the install's); a Type=notify unit waits for READY=1 without a
    start timeout: with the broker down at boot, the default 90 s failed the start and
    restarted the unit in a loop."""
    exe = Path(sys.executable).parent / "pseudotwin"  # this venv's
    assert exe.exists()
    units = sorted(DEPLOY.glob("*.service"))
    assert [u.name for u in units] == ["pseudotwin-bridge.service",
                                       "pseudotwin-recorder.service", "pseudotwin.service"]
    for unit in units:
        text = unit.read_text(encoding="utf-8")
        assert "ExecStart=/opt/pseudotwin/bin/pseudotwin " in text
        if "Type=notify" in text:
            assert "\nTimeoutStartSec=infinity\n" in text, unit.name
        (tmp_path / unit.name).write_text(text.replace("/opt/pseudotwin/bin/pseudotwin",
                                                       str(exe)), encoding="utf-8")
    # The fleet's template: the daemon's unit under a template name, beside its drop-in.
    shutil.copy(tmp_path / "pseudotwin.service", tmp_path / "pseudotwin@.service")
    shutil.copytree(DEPLOY / "pseudotwin@.service.d", tmp_path / "pseudotwin@.service.d")
    files = [*map(str, sorted(tmp_path.glob("*.service"))),
             str(tmp_path / "pseudotwin@1-4.service")]
    done = subprocess.run(["systemd-analyze", "verify", *files],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr


@pytest.mark.skipif(shutil.which("systemd-escape") is None, reason="no systemd-escape")
def test_a_fleet_instance_of_the_template_runs_its_shard() -> None:
    """pseudotwin@1-4.service: the unit's command line with the drop-in's options, the
    instance name unescaped by systemd as %I, is `run --shard 1/4`; the plain unit passes no
    option (an unset variable as a word of its own is no argument)."""
    from pseudotwin.cli import build_parser
    from pseudotwin.edge.fleet import Shard

    unit = (DEPLOY / "pseudotwin.service").read_text(encoding="utf-8")
    exec_start = re.search(r"^ExecStart=(.*)$", unit, re.M)
    assert exec_start is not None
    words = exec_start.group(1).split()
    assert words[-1] == "$PSEUDOTWIN_RUN_ARGS"
    plain = build_parser().parse_args(words[1:-1])
    assert plain.command == "run" and plain.shard is None
    dropin = (DEPLOY / "pseudotwin@.service.d" / "fleet.conf").read_text(encoding="utf-8")
    env = re.search(r'^Environment="PSEUDOTWIN_RUN_ARGS=(.*)"$', dropin, re.M)
    assert env is not None
    instance = subprocess.run(["systemd-escape", "-u", "1-4"], capture_output=True,
                              text=True, check=True).stdout.strip()
    argv = [*words[1:-1], *env.group(1).replace("%I", instance).split()]
    fleet = build_parser().parse_args(argv)
    assert fleet.shard == Shard(1, 4) and fleet.config == Path("/etc/pseudotwin/config.toml")


def test_the_image_and_the_tests_share_one_pinned_set_of_dependencies() -> None:
    """The image's build took whatever PyPI held that day (pyproject has lower bounds only):
    a numerical stack no test had run, for a daemon whose σ is meant to be reproducible."""
    from importlib.metadata import version

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    pins = {}
    for line in (DEPLOY / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, _, pinned = line.partition("==")
            pins[canonicalize_name(name)] = pinned
    project = tomllib.loads((DEPLOY.parent / "pyproject.toml").read_text())["project"]
    for dep in map(Requirement, project["dependencies"]):
        name = canonicalize_name(dep.name)
        assert name in pins, f"{dep.name} is not pinned in deploy/constraints.txt"
        assert dep.specifier.contains(pins[name]), (dep, pins[name])
    for name, pinned in pins.items():  # what the suite runs with (bootstrap.sh uses them)
        assert version(name) == pinned, name
    docker = (DEPLOY / "Dockerfile").read_text()
    assert "COPY deploy/constraints.txt" in docker and "-c deploy/constraints.txt ." in docker
    assert "-c deploy/constraints.txt" in (DEPLOY.parent / "scripts/bootstrap.sh").read_text()
