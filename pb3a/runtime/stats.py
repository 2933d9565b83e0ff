"""Gathering ``Running.stats()``: one request to every worker, merged per module and link."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pb3a.errors import RuntimeFailure, RuntimeTimeout

if TYPE_CHECKING:
    from pb3a.runtime.executor import Executor


def collect(executor: Executor, timeout: float = 5.0) -> dict[str, Any]:
    """Figures of every module and link of one executor."""
    futures = {key: executor.submit(key, "stats")
               for key, handle in list(executor.workers.items()) if handle.alive}
    reports: dict[str, Any] = {}
    for key, future in futures.items():
        try:
            reports[key] = executor.result(future, "stats", key, timeout)
        except (RuntimeFailure, RuntimeTimeout):
            continue
    modules: dict[str, Any] = {}
    ports: dict[tuple[str, str], Any] = {}
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
        for port, figures in entry["inputs"].items():
            ports[(name, port)] = figures
        modules[name] = entry
    links = {}
    for key, link in executor.links.items():
        figures = ports.get((link.dst, link.dst_port), {})
        src = executor.modules.get(link.src)
        dst = executor.modules.get(link.dst)
        remote = bool(src and dst and executor.remote(link))
        transport = ("zmq" if remote else
                     "memory" if src and dst and src.worker == dst.worker else "shm")
        lost = executor.bridge.link_failures(f"{link.src}.{link.src_port}") if remote else 0
        ring = reports.get(dst.worker, {}).get("rings", {}).get(key, {}) if dst else {}
        links[key] = {"src": f"{link.src}.{link.src_port}", "dst": f"{link.dst}.{link.dst_port}",
                      "policy": str(link.policy), "transport": transport,
                      "values": figures.get("received", 0), "drops": figures.get("drops", 0),
                      "pending": figures.get("pending", 0),
                      "latency": figures.get("latency", float("nan")),
                      "rate": figures.get("rate", 0.0),
                      "link_failures": figures.get("link_failures", 0) + lost,
                      "ring_bytes_used": ring.get("used", 0)}
    return {"modules": modules, "links": links, "failures": list(executor.failures)}
