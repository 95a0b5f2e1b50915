"""What the node says: its ``/diagnostics`` status, why its data is stale, and the answer of a tare
service; from the stream's health, the source's link and the node's state (no per-frame work)."""
from __future__ import annotations

import math
import time

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from ..frame_path.health import ERROR, OK, WARN


def stale_reason(cfg, stream, source) -> str:
    """Why the data is stale ('' when fresh)."""
    if cfg is None or stream is None:
        return "not configured"
    last = stream.counter.counts.last_frame
    age = math.inf if last is None else time.monotonic() - last
    if age <= cfg.stream.stale_timeout:
        return ""
    what = "no frames yet" if last is None else f"no frames for {age:.1f} s (stale_timeout {cfg.stream.stale_timeout} s)"
    driver = getattr(source, "driver", None)
    if driver is not None:
        ds = driver.stats()
        if not ds.connected:
            what += f"; board disconnected ({ds.last_error or 'port not open'})"
        elif ds.last_error:
            what += f"; last error: {ds.last_error}"
    elif source is not None and getattr(source, "subscription", None) is not None \
            and source.stats()["publishers"] == 0:
        what += f"; nobody publishes {source.subscription.topic_name}"
    return what


def diagnostics(node) -> DiagnosticStatus:
    """The node's DiagnosticStatus now (resets the per-period figures): the stream's health, the
    board's link, the staleness and the messages published per topic."""
    cfg, stream, active = node.config, node.stream, node.active
    serial = cfg is not None and cfg.input == "serial"
    status = DiagnosticStatus(name=node.diagnostics_name, hardware_id=cfg.port if serial else "")
    kv = {"state": "active" if active else "inactive", "input": cfg.input if cfg else "",
          "reference": node.reference_source}
    level, msgs = OK, []
    driver = node.driver
    ds = driver.stats() if driver is not None else None
    board = None
    if ds is not None:
        kv.update(connected=ds.connected, dropped_overflow=ds.dropped_overflow, reconnects=ds.reconnects,
                  seq_gaps=ds.seq_gaps, duplicates=ds.duplicates, reordered=ds.reordered, resyncs=ds.resyncs,
                  frame_period_ms=f"{ds.period * 1e3:.1f}", last_error=ds.last_error)
        board = dict(corrupt=ds.corrupt, gaps=ds.seq_gaps, duplicates=ds.duplicates, reordered=ds.reordered,
                     overflow=ds.dropped_overflow)
        if not ds.connected:
            level, msgs = ERROR, ["board disconnected"]
    if stream is not None:
        s_level, s_msgs, s_kv = stream.end_period(time.monotonic(), board)
        level, msgs = max(level, s_level), msgs + s_msgs
        kv.update(s_kv)
    kv["checksum"] = ("crc32" if cfg.protocol == "binary" else "none (text mode)") if serial else "n/a"
    reason = node.stale_reason() if active else ""
    kv["stale_reason"] = reason
    kv["messages_published"] = " ".join(f"{t}={n}" for t, n in sorted(dict(node.published).items()))
    if reason:
        level = ERROR if ds is not None and not ds.connected else max(level, WARN)
        msgs = [f"stale: {reason}"] + [m for m in msgs if m != "board disconnected"]  # the reason says it
    status.level = bytes([level])  # diagnostic_msgs' levels are bytes
    status.message = "; ".join(msgs) or ("streaming" if active else "inactive")
    status.values = [KeyValue(key=k, value=str(v)) for k, v in kv.items()]
    return status


def tare_answer(node, outcome, taken: int, wait: float, forced: bool) -> tuple[bool, str]:
    """(success, message) of a tare service (``~/tare``, ``~/tare_forced``) whose transaction ended
    with ``outcome`` (None: cancelled after ``wait`` s, ``taken`` frames in)."""
    stream, n = node.stream, node.config.stream.tare_frames
    unchanged = f"the reference ({node.reference_source}) and {node.tare_path} are unchanged"
    name = "~/tare_forced" if forced else "~/tare"
    if outcome is None:
        why = node.stale_reason() or "frames late, dropped or rejected"
        msg = f"tare cancelled: {taken} of {n} frames within {wait:.1f} s ({why}); {unchanged}; call {name} " \
              "again once frames arrive"
        if stream.tares.pending:
            msg += " (the tare at start stays pending: no reference yet)"
        node.get_logger().warning(msg)
        return False, msg
    if not outcome.ok:
        msg = f"{outcome.reason}, then call {name} again; {unchanged}"
        if outcome.check is not None and outcome.check.problems():
            msg += ("; if the joint is unloaded and the change is the device's own (warmed unevenly, contacts "
                    "changed), ~/tare_forced takes it")
        return False, msg
    check = outcome.check.summary() if outcome.check is not None else "no load check"
    forced_note = ""
    if outcome.forced:
        forced_note = f"forced tare, overrode: {outcome.overridden}; " if outcome.overridden else \
                      "forced tare (the load checks passed anyway); "
    return True, (f"{forced_note}reference from {n} frames (spread {outcome.spread:.2%} of its rms; "
                  f"{check}); {outcome.note or node.reference_source}")
