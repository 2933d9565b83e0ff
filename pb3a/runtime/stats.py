"""Gathering ``Running.stats()``: each node reports its modules and inputs (one request
to each of its workers); the launcher joins the reports into the per-link table."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout

if TYPE_CHECKING:
    from pb3a.kernel.config import FlatLink
    from pb3a.runtime.executor import Executor


def node_report(executor: Executor, timeout: float = 5.0) -> dict[str, Any]:
    """Figures of every module of one node, its rings and its remote links' losses."""
    futures = {key: executor.submit(key, "stats")
               for key, handle in list(executor.workers.items()) if handle.alive}
    reports: dict[str, Any] = {}
    for key, future in futures.items():
        try:
            reports[key] = executor.result(future, "stats", key, timeout)
        except (RuntimeFailure, RuntimeTimeout):
            continue
    modules: dict[str, Any] = {}
    for name, record in executor.modules.items():
        entry = {"node": record.spec.node, "worker": record.worker, "status": record.status,
                 "restarts": record.restarts, "checkpoints": record.checkpoints, "pid": None,
                 "steps": 0, "events": 0, "errors": 0, "cpu": 0.0, "last_error": "",
                 "inputs": {}, "outputs": {}}
        report = reports.get(record.worker)
        if report is not None and name in report["modules"]:
            entry.update(report["modules"][name])
            entry["pid"] = report["pid"]
            entry["running"] = entry["running"] and record.status == "running"
        modules[name] = entry
    rings = {key: ring.get("used", 0) for report in reports.values()
             for key, ring in report.get("rings", {}).items()}
    lost = {key: executor.bridge.link_failures(f"{link.src}.{link.src_port}")
            for key, link in executor.inbound.items()}
    return {"modules": modules, "rings": rings, "lost": lost,
            "failures": list(executor.failures)}


def link_table(links: dict[str, FlatLink], modules: dict[str, Any],
               reports: list[dict[str, Any]]) -> dict[str, Any]:
    """Per link: values, drops, pending, latency, rate, transport, from the reader's node."""
    rings = {key: used for report in reports for key, used in report["rings"].items()}
    lost = {key: count for report in reports for key, count in report["lost"].items()}
    table = {}
    for key, link in links.items():
        src, dst = modules.get(link.src), modules.get(link.dst)
        figures = dst["inputs"].get(link.dst_port, {}) if dst else {}
        transport = ("zmq" if src and dst and src["node"] != dst["node"] else
                     "memory" if src and dst and src["worker"] == dst["worker"] else "shm")
        table[key] = {"src": f"{link.src}.{link.src_port}", "dst": f"{link.dst}.{link.dst_port}",
                      "policy": str(link.policy), "transport": transport,
                      "values": figures.get("received", 0), "drops": figures.get("drops", 0),
                      "pending": figures.get("pending", 0),
                      "latency": figures.get("latency", float("nan")),
                      "rate": figures.get("rate", 0.0),
                      "link_failures": figures.get("link_failures", 0) + lost.get(key, 0),
                      "ring_bytes_used": rings.get(key, 0)}
    return table
