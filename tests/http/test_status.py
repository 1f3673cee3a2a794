"""The status page (``GET /``, ``GET /status.json``) in a real headless Chromium, and the
Grafana dashboard's queries against a real gateway's ``/metrics``."""

from __future__ import annotations

import json
import re
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from html.parser import HTMLParser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar, cast

import httpx
import promql_parser
import pytest
from prometheus_client.parser import text_string_to_metric_families
from selenium import webdriver
from selenium.common.exceptions import NoAlertPresentException
from selenium.webdriver.chrome.options import Options
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By

from antireplay.audit import AuditLog, sanitize, tail
from antireplay.audit.segments import rotated
from antireplay.cli.demo import JSON, command, load_operator_key, write_demo_config
from antireplay.http.status import AUDIT_COLUMNS, _audit, render, security_headers
from antireplay.rcan.receive import Receiver
from harness import ROOT, GatewayProcess, metrics_pq, metrics_router, post, serving
from harness.audit import segmented, trail
from harness.redis_server import RedisServer
from harness.stores import aged_state

DASH = "\u2014"
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
DASHBOARD = ROOT / "dashboards" / "antireplay-grafana.json"
HOSTILE_MSG_ID = "<script>alert(1)</script>"
HOSTILE_SENDER = "op\" onmouseover='alert(2)"
#: A state directory whose name is markup: the audit trail's path is shown on the page.
HOSTILE_DIR = "<img src=x onerror=alert(3)> \"quoted\" 'single'"


@contextmanager
def chromium(profile: Path) -> Iterator[webdriver.Chrome]:
    """Headless Debian Chromium driven by its chromedriver, console captured; missing
    binaries fail the test (CI installs them), never skip it."""
    for binary in (CHROMIUM, CHROMEDRIVER):
        if shutil.which(binary) is None:
            pytest.fail(f"{binary} is missing: apt-get install -y chromium chromium-driver")
    options = Options()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu"):
        options.add_argument(arg)
    options.add_argument(f"--user-data-dir={profile}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def console_errors(driver: webdriver.Chrome) -> list[dict[str, Any]]:
    entries: list[dict[str, Any]] = driver.get_log("browser")  # type: ignore[no-untyped-call]
    return [e for e in entries if e["level"] in ("SEVERE", "WARNING")]


def no_alert(driver: webdriver.Chrome) -> bool:
    try:
        _ = driver.switch_to.alert
    except NoAlertPresentException:
        return True
    return False


def table(driver: webdriver.Chrome, ident: str) -> dict[str, str]:
    """A two-column table of the page as {header: value}."""
    rows = driver.find_element(By.ID, ident).find_elements(By.TAG_NAME, "tr")
    return {
        r.find_element(By.TAG_NAME, "th").text: r.find_element(By.TAG_NAME, "td").text
        for r in rows
        if r.find_elements(By.TAG_NAME, "th")
    }


@pytest.fixture(scope="module")
def state(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("status") / HOSTILE_DIR
    path.mkdir()
    return path


@pytest.fixture(scope="module")
def gateway(state: Path) -> Iterator[GatewayProcess]:
    """A real ``antireplay serve`` that has accepted one command, refused its replay, accepted
    one with a markup msg_id and refused a forgery claiming a markup sender."""
    config = write_demo_config(state)
    aged_state(state / "state.db")  # a deployment started earlier: no first-start row
    with serving(config) as process:
        key = load_operator_key(state)
        accepted = command(key)
        assert post(process, accepted).status_code == 200
        assert post(process, accepted).status_code == 409
        assert post(process, command(key, msg_id=HOSTILE_MSG_ID)).status_code == 200
        forged = {**json.loads(command(key, sender=HOSTILE_SENDER)), "cmd": "self_destruct"}
        assert post(process, json.dumps(forged).encode()).status_code == 401
        yield process


def test_status_page_renders_in_chromium_without_console_errors(
    gateway: GatewayProcess, state: Path, tmp_path: Path
) -> None:
    with chromium(tmp_path / "profile") as driver:
        driver.get(f"{gateway.url}/")
        assert driver.title == "antireplay status"
        assert driver.find_element(By.ID, "readiness").text.startswith("ready")
        counters = table(driver, "counters")
        assert (counters["accepted"], counters["rejected"]) == ("2", "2")
        assert table(driver, "rejected-by-code") == {
            "REPLAY_DETECTED": "1",
            "SIGNATURE_INVALID": "1",
        }
        store = table(driver, "store-health")
        assert (store["backend"], store["entries"], store["data-loss events"]) == (
            "sqlite",
            "2",
            "0",
        )
        rows = driver.find_element(By.ID, "audit").find_elements(By.TAG_NAME, "tr")[1:]
        cells = [[td.text for td in row.find_elements(By.TAG_NAME, "td")] for row in rows]
        assert [c[2:4] for c in cells] == [  # newest first: outcome, code (none: a dash)
            ["rejected", "SIGNATURE_INVALID"], ["accepted", DASH], ["rejected", "REPLAY_DETECTED"],
            ["accepted", DASH],
        ]  # fmt: skip
        assert cells[1][7] == sanitize(HOSTILE_MSG_ID)  # shown as its hash, inert
        assert cells[0][6] == f"{sanitize(HOSTILE_SENDER)} (claimed)"
        caption = driver.find_element(By.CSS_SELECTOR, "#audit caption").text
        assert HOSTILE_DIR in caption  # the markup directory name is text on the page
        assert driver.find_elements(By.TAG_NAME, "script") == []
        assert driver.find_elements(By.TAG_NAME, "img") == []
        assert no_alert(driver)
        assert console_errors(driver) == []
        assert tail(state / "audit.db", 100)[-1].code == "SIGNATURE_INVALID"  # nothing recorded


def test_the_console_check_sees_a_csp_violation(tmp_path: Path) -> None:
    """If escaping ever failed, the page's own headers still stop an injected script, and
    the console check above would see the violation (so its empty console means something)."""
    nonce = "n0nce"
    page = render(_snapshot_with("<script>document.title='owned'</script>"), nonce)
    page = page.replace("</footer>", "</footer><script>document.title='owned'</script>")

    class Handler(BaseHTTPRequestHandler):
        headers_sent: ClassVar[dict[str, str]] = security_headers(nonce)

        def do_GET(self) -> None:
            body = page.encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            for name, value in self.headers_sent.items():
                self.send_header(name, value)
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with chromium(tmp_path / "profile") as driver:
            driver.get(f"http://127.0.0.1:{server.server_port}/")
            assert driver.title == "antireplay status"  # the script did not run
            errors = console_errors(driver)
            assert any("Content Security Policy" in e["message"] for e in errors), errors
    finally:
        server.shutdown()
        server.server_close()


def test_status_json_is_the_page_data_and_matches_metrics(gateway: GatewayProcess) -> None:
    reply = httpx.get(f"{gateway.url}/status.json", timeout=10)
    page = httpx.get(f"{gateway.url}/", timeout=10)
    for response in (reply, page):
        assert response.status_code == 200
        assert response.headers["x-content-type-options"] == "nosniff"
        assert response.headers["cache-control"] == "no-store"
        assert response.headers["content-security-policy"].startswith("default-src 'none'; ")
    assert "script-src" not in page.headers["content-security-policy"]
    data = reply.json()
    assert data["ready"] is True and data["reason"] is None
    assert None not in data["counters"].values()  # every name it reads is still exported
    assert set(data["group_commit"]) == {"state", "audit"}
    assert data["counters"]["accepted"] == 2
    assert data["counters"]["rejected"] == {"REPLAY_DETECTED": 1, "SIGNATURE_INVALID": 1}
    assert data["store"]["backend"] == "sqlite" and data["store"]["entries"] == 2
    assert [r["code"] for r in data["audit"]["records"]][:2] == ["SIGNATURE_INVALID", None]
    assert "params" not in json.dumps(data) and "distance_m" not in json.dumps(data)
    metrics = httpx.get(f"{gateway.url}/metrics", timeout=10).text
    assert "antireplay_accepted_total 2.0" in metrics
    assert 'antireplay_rejected_total{code="REPLAY_DETECTED"} 1.0' in metrics


def test_the_status_page_records_nothing(gateway: GatewayProcess, state: Path) -> None:
    before = httpx.get(f"{gateway.url}/status.json", timeout=10).json()
    rows = len(tail(state / "audit.db", 10_000))
    for path in ("/", "/status.json") * 10:
        assert httpx.get(f"{gateway.url}{path}", timeout=10).status_code == 200
    after = httpx.get(f"{gateway.url}/status.json", timeout=10).json()
    assert (after["counters"], after["store"]) == (before["counters"], before["store"])
    assert len(tail(state / "audit.db", 10_000)) == rows
    refused = httpx.post(f"{gateway.url}/status.json", content=b"{}", headers=JSON, timeout=10)
    assert refused.status_code == 405


def test_status_page_shows_the_store_down_and_still_answers(tmp_path: Path) -> None:
    redis_server = RedisServer(tmp_path)
    redis_server.start()
    gateway = GatewayProcess(write_demo_config(tmp_path, store=redis_server.url))
    gateway.start()
    try:
        answered = post(gateway, command(load_operator_key(tmp_path)))  # or the restart fence
        assert answered.status_code in (200, 408), answered.text
        redis_server.stop()
        data = httpx.get(f"{gateway.url}/status.json", timeout=10).json()
        assert data["ready"] is False
        assert "store: STATE_UNAVAILABLE" in data["reason"]
        assert data["store"]["backend"] == "redis" and data["store"]["entries"] is None
        counters = data["counters"]
        assert counters["accepted"] + counters["rejected_total"] == 1
        newest = data["audit"]["records"][0]  # the trail is a file: still readable
        assert newest["outcome"] == ("accepted" if answered.status_code == 200 else "rejected")
        page = httpx.get(f"{gateway.url}/", timeout=10)
        assert page.status_code == 200 and "not ready: store: STATE_UNAVAILABLE" in page.text
    finally:
        gateway.stop()
        redis_server.stop()


def _snapshot_with(hostile: str) -> dict[str, Any]:
    """A snapshot whose every string is ``hostile`` (as if nothing had been sanitized)."""
    record = dict.fromkeys(AUDIT_COLUMNS, hostile) | {"at": 1.0, "sender_verified": False}
    counters: dict[str, Any] = dict.fromkeys(
        ("accepted", "rejected_total", "store_errors", "upstream_errors",
         "restart_fence_rejections", "latency_observations"),
        hostile,
    )  # fmt: skip
    for labelled in ("rejected", "warnings", "replay_refusals"):
        counters[labelled] = {hostile: hostile}
    store = dict.fromkeys(
        ("backend", "entries", "watermark", "fence", "data_loss_events", "watermark_raises"),
        hostile,
    )
    return {
        "generated_at": hostile,
        "ready": False,
        "reason": hostile,
        "counters": counters,
        "store": store,
        "group_commit": {hostile: {"batches": hostile, "operations": hostile}},
        "audit": {"path": hostile, "records": [record], "error": None},
    }


class _Elements(HTMLParser):
    """Every start tag and attribute name of a document."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: set[str] = set()
        self.attributes: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.add(tag)
        self.attributes.update(name for name, _ in attrs)


@pytest.mark.parametrize(
    "hostile",
    [
        HOSTILE_MSG_ID,
        HOSTILE_SENDER,
        '"><img src=x onerror=alert(1)>',
        "</table></style><script>alert(1)</script>",
        "&lt;script&gt;",
    ],
)
def test_render_escapes_every_value_even_unsanitized(hostile: str) -> None:
    page = render(_snapshot_with(hostile), "nonce")
    elements = _Elements()
    elements.feed(page)
    assert "script" not in elements.tags and "img" not in elements.tags
    assert not any(name.startswith("on") for name in elements.attributes)
    assert hostile not in page  # only its escaped form is


def _exported(metrics_text: str) -> set[str]:
    """Every series name a /metrics text can carry, with the suffixes of its type."""
    suffixes = {"counter": ("_total", "_created"), "histogram": ("_bucket", "_sum", "_count")}
    names: set[str] = set()
    for family in text_string_to_metric_families(metrics_text):
        names.add(family.name)
        names.update(family.name + s for s in suffixes.get(family.type, ()))
        names.update(sample.name for sample in family.samples)
    return names


@contextmanager
def router_metrics_text(tmp_path: Path) -> Iterator[str]:
    """What a real ``antireplay mavlink-router --metrics-port`` exports."""
    with metrics_router(tmp_path) as port:
        yield httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text


@contextmanager
def pq_metrics_text(tmp_path: Path) -> Iterator[str]:
    """What a real ``antireplay mavlink-pq ground --metrics-port`` exports."""
    with metrics_pq(tmp_path) as port:
        yield httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=10).text


def _names(query: str) -> set[str]:
    """The metrics a ``label_values(METRIC, label)`` variable query reads."""
    return set(re.findall(r"\bantireplay_[a-z0-9_]+\b", query))


def _selected(expr: str) -> set[str]:
    """The metric of every selector of a PromQL expression, parsed by Prometheus' own
    grammar (a query with a syntax error fails here, as it would in Grafana)."""
    names: set[str] = set()

    def visit(node: object) -> None:
        if isinstance(node, promql_parser.VectorSelector):
            names.add(node.name or "")

    promql_parser.walk(promql_parser.parse(expr.replace("$__rate_interval", "5m")), visit)
    return names


def test_the_dashboard_queries_only_metrics_that_are_exported(
    gateway: GatewayProcess, tmp_path: Path
) -> None:
    """Every metric of every query is exported by a real gateway (a renamed metric fails
    here), the MAVLink row's by a real router, the post-quantum row's by a real PQ end."""
    dashboard = json.loads(DASHBOARD.read_text())
    assert dashboard["schemaVersion"] >= 38  # Grafana 10+
    variables = {v["name"]: v for v in dashboard["templating"]["list"]}
    assert (variables["DS_PROMETHEUS"]["type"], variables["DS_PROMETHEUS"]["query"]) == (
        "datasource",
        "prometheus",
    )
    panels = dashboard["panels"]
    ids = [p["id"] for p in panels]
    assert len(ids) == len(set(ids))
    gateway_names = _exported(httpx.get(f"{gateway.url}/metrics", timeout=10).text)
    with router_metrics_text(tmp_path) as text:
        router_names = _exported(text)
    with pq_metrics_text(tmp_path) as text:
        pq_names = _exported(text)
    assert _names(variables["instance"]["definition"]) <= gateway_names
    assert _names(variables["router"]["definition"]) <= router_names
    assert _names(variables["pq"]["definition"]) <= pq_names
    used: set[str] = set()
    exported = gateway_names
    for panel in panels:
        if panel["type"] == "row":
            rows = {"MAVLink router": router_names, "Post-quantum MAVLink": pq_names}
            title = panel["title"]
            exported = next((v for k, v in rows.items() if title.startswith(k)), gateway_names)
            continue
        assert panel["datasource"]["uid"] == "${DS_PROMETHEUS}", panel["title"]
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            assert target["datasource"]["uid"] == "${DS_PROMETHEUS}", panel["title"]
            names = _selected(target["expr"])
            assert names, f"{panel['title']}: {target['expr']} selects nothing"
            assert names <= exported, f"{panel['title']}: {sorted(names - exported)} not exported"
            used |= names
    wanted = {
        "antireplay_accepted_total", "antireplay_rejected_total", "antireplay_warnings_total",
        "antireplay_latency_seconds_bucket", "antireplay_store_errors_total",
        "antireplay_state_data_loss_total", "antireplay_state_fence_seconds",
        "antireplay_state_watermark_seconds", "antireplay_cache_entries",
        "antireplay_group_commit_batches_total", "antireplay_group_commit_operations_total",
        "antireplay_replay_refusals_total", "antireplay_mavlink_forwarded_total",
        "antireplay_mavlink_dropped_total", "antireplay_mavlink_pq_sessions_total",
        "antireplay_mavlink_pq_session_up", "antireplay_mavlink_pq_handshakes_total",
        "antireplay_mavlink_pq_chunks_total", "antireplay_mavlink_pq_refusals_total",
        "antireplay_mavlink_pq_dropped_total", "antireplay_mavlink_pq_unaudited_total",
    }  # fmt: skip
    assert wanted <= used, sorted(wanted - used)


def test_status_page_names_what_the_window_refusals_table_counts() -> None:
    """The table shows the window's refusals (fence and store included), not every replay:
    a byte-identical copy refused at step 0 is in "Rejected by code" only, so the heading
    says so instead of claiming "Replay refusals"."""
    page = render(_snapshot_with("x"), "nonce")
    assert "Replay refusals by cause" not in page
    assert "Replay-window refusals by cause" in page
    assert "byte-identical copies count under Rejected by code only" in page


def test_status_says_the_trail_was_deleted_under_the_running_gateway(tmp_path: Path) -> None:
    """Deleted while serving: the status page speaks of the running gateway, not of a start."""
    trail(tmp_path / "audit.db", 1)
    log = AuditLog(tmp_path / "audit.db")
    try:
        (tmp_path / "audit.db").unlink()
        said = _audit(cast(Receiver, SimpleNamespace(audit=log)), 5)["error"]
    finally:
        log.close()
    assert "deleted under the running gateway" in said
    assert "refusing to start" not in said
    assert "audit reanchor" in said


def test_the_status_page_shows_the_newest_records_across_segments(tmp_path: Path) -> None:
    """Just rotated: the live segment holds a few rows, the page still shows the last 30."""
    log = segmented(tmp_path / "audit.db", 140)
    try:
        shown_ids = [
            r["msg_id"] for r in _audit(cast(Receiver, SimpleNamespace(audit=log)), 30)["records"]
        ]
    finally:
        log.close()
    assert len(rotated(tmp_path / "audit.db")) >= 3
    assert sorted(shown_ids, key=lambda m: int(m[1:])) == [f"m{i}" for i in range(110, 140)]
