"""``quick-stream bench pipeline``'s text: one run's report (:func:`format_report`) and the delay each
``--latency`` preset gives as the viewer sees it (:func:`format_presets`)."""
from __future__ import annotations

from ..core.params import user_defaults
from .pipeline_profile import format_profile

DEFAULT_PRESET = str(user_defaults()["latency"])  # the motion service's --latency when none is given


def format_report(r: dict) -> str:
    per = r["streams"] if "streams" in r else {"": r}
    lines = []
    for cam, x in per.items():
        preset = f", --latency {r['latency_preset']}" if "latency_preset" in r else ""
        lines.append(f"pipeline {cam + ' ' if cam else ''}{r['size']} at {r['fps_target']} fps{preset} for {r['seconds']:g} s "
                     f"({r['capture']}), recording {'on' if r['recording'] else 'off'}: sent {x['frames_sent']}, "
                     f"stabilized {x['frames_stabilized']} ({x['stabilized_fps']} fps), flagged {x['frames_flagged']}, "
                     f"drops {x['drops'] or 'none'}")
        for k, v in x["latency"].items():
            if v:
                lines.append(f"  latency {k:<29} p50 {v['p50']:7.1f}  p90 {v['p90']:7.1f}  p99 {v['p99']:7.1f}  "
                             f"max {v['max']:7.1f} ms  (n={v['n']})")
        steps = x.get("release_steps_ms")
        if steps:
            lines.append("  first frame of a release, by step (the recorder's arrival times): " + (
                steps["error"] if "error" in steps else ", ".join(
                    f"{k} p50 {v['p50']:.1f} p90 {v['p90']:.1f} ms" for k, v in steps.items())
                + f" (n={max(v['n'] for v in steps.values())})"))
        if len(x.get("latency_p99_per_minute", [])) > 1:
            lines.append("  total latency p99 per minute (ms): "
                         + " ".join(f"{w['total_p99_ms']:.0f}" for w in x["latency_p99_per_minute"]))
    cpu = r.get("cpu_per_frame") or {}
    lines.append(f"  {'process':<15} {'CPU %':>6} {'ms/frame':>8} {'core fps':>8} {'RSS warm':>9} {'RSS end':>8} "
                 f"{'growth':>7} {'peak RSS':>9} (MB)   RSS over the run, from start-up")
    for name, p in r["processes"].items():
        per = cpu.get("ms", {}).get(name)
        alone = f"{1000.0 / per:.0f}" if per else "-"  # frames/s on a core of its own, if its CPU bounds it
        lines.append(f"  {name:<15} {p['cpu_pct']:>6.1f} {'-' if per is None else f'{per:.1f}':>8} {alone:>8} "
                     f"{p['rss_mb_warm']:>9.1f} {p['rss_mb_end']:>8.1f} {p['rss_growth_pct']:>6.1f}% "
                     f"{p['peak_rss_mb']:>9.1f}        {' '.join(f'{x:.0f}' for x in p['rss_mb_series'])}")
    if cpu:
        lines.append(f"  CPU per stabilized frame: {cpu['total_ms']:.1f} ms of the {cpu['budget_ms']:.1f} ms that "
                     f"{cpu['cores']} cores give per frame at {cpu['rate_fps']:g} fps "
                     f"({100.0 * cpu['total_ms'] / cpu['budget_ms']:.0f} % used)")
    if r.get("queues"):
        lines.append("  queue lengths after warm-up, sampled each second (max in the first half/max in the second "
                     "half/mean): " + ", ".join(f"{k} {q['max_first_half']:.0f}/{q['max_second_half']:.0f}/"
                                                f"{q['mean']:g}" for k, q in r["queues"].items()))
    if r.get("profile"):
        lines.append(format_profile(r["profile"]["threads"], r["profile"]["functions"]))
    return "\n".join(lines)


def format_presets(reports: list[dict]) -> str:
    """Each run's delay as the viewer sees it, one row per rate and ``--latency`` preset: a stabilized
    frame's publication after its capture's (total: p50/p99 and max), of which the wait for the
    segment that releases it (the look-ahead) and the processing after that."""
    lines = ["delay from capture to the stabilized frame's publication, per --latency preset (ms):",
             f"  {'preset':<10} {'fps':>5} {'total p50':>10} {'p99':>7} {'max':>7} {'wait p50':>9} "
             f"{'processing p99':>15} {'stabilized':>11} {'flagged':>8} {'shed':>5}"]
    for r in reports:
        for cam, x in (r["streams"] if "streams" in r else {"": r}).items():
            lat = x.get("latency", {})
            tot, wait, proc = (lat.get(k) or {} for k in ("total_ms", "segment_wait_ms", "processing_ms"))
            shed = sum(v for k, v in x.get("drops", {}).items() if k.endswith("shed"))
            name = r.get("latency_preset", DEFAULT_PRESET) + (f" {cam}" if cam else "")
            lines.append(f"  {name:<10} {r['fps_target']!s:>5} {tot.get('p50', float('nan')):>10.0f} "
                         f"{tot.get('p99', float('nan')):>7.0f} {tot.get('max', float('nan')):>7.0f} "
                         f"{wait.get('p50', float('nan')):>9.0f} {proc.get('p99', float('nan')):>15.0f} "
                         f"{x['frames_stabilized']:>11} {x['frames_flagged']:>8} {shed:>5}")
    return "\n".join(lines)
