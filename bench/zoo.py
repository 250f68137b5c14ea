"""The residual loop on records others made (``test/external_records.py``: another team's simulated valves, a measured
micromanipulator), quiet and beside two busy loops, and on valves written from the literature's equations
(``test/valve_zoo.py``), and how stable its judgement is: each zoo valve and each of the battery's valves recorded five times (other noise seeds and training
records 0-15 % shorter), with what it named every time.

    python bench/zoo.py [--markdown docs/results/identification/zoo.md] [--records 5] [--external-only]

Per case: what is right for it (the names it may give, and the ones it must give unless it says unexplained), the
judgement on the first record (names, unexplained, held-out RMS before and after at the record's rate, seconds),
whether that is right, and over all records: what each said, how many name the same effects as the most common
judgement (a stable judgement names the same effects; how often it also said unexplained is counted apart) and
how many are right.
"""
import argparse
import collections
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "test"))

import valve_zoo as zoo                                        # noqa: E402  (test code, not the package's)
import valve_battery as battery                                # noqa: E402
import external_records as external                            # noqa: E402
from harness import busy_loops, host_yardstick, yardstick_note  # noqa: E402
from piezo_valve_ros.core.identification import Record  # noqa: E402
from piezo_valve_ros.runtime import keep_freed_memory  # noqa: E402
from piezo_valve_ros.core.identification import analyse  # noqa: E402

RECORDS = ((1, 1.0), (2, 0.85), (3, 1.0), (4, 0.9), (5, 0.95))   # (seed, training length share) of each record
EXTERNAL_NOTE = ("## Records others made\n\nOutput of `python bench/zoo.py {command}`: the records in "
                 "`test/data/external_records` (provenance in its README: three valves another team simulated with its "
                 "own code, decimated to 1 kHz, and a measured micromanipulator pair at 200 Hz), each trained on its "
                 "training session and judged on its separate validation session; 'right': the truth's names exactly "
                 "(`unexplained` may be either), for the micromanipulator what a good analysis achieves.  Held-out "
                 "figures at the record's rate; seconds of one analysis, quiet and with two busy loops beside on this "
                 "2-core machine.")


def judge(train_rows, validate_rows) -> tuple[dict, float]:
    started = time.monotonic()
    report = analyse(Record(train_rows[:, 0], train_rows[:, 1], train_rows[:, 2]),
                     Record(validate_rows[:, 0], validate_rows[:, 1], validate_rows[:, 2])).report.to_json()
    return report, time.monotonic() - started


def names(report: dict) -> str:
    return ", ".join(report["effects_added"]) or "none"


def story(report: dict) -> str:
    return names(report) + (" (unexplained)" if report["unexplained"] else "")


def zoo_records(case, seed, share):
    return case.records(seed, share)


def battery_records(valve, seed, share):
    """A battery valve's training (shortened to ``share`` of its main part) and validation records."""
    train_v = battery.training_voltage(battery.DT)
    train_v = train_v[: int(share * train_v.size)]
    rows_t = valve.rows(train_v, seed)
    rows_v = valve.rows(battery.validation_voltage_(battery.DT), seed + 100)
    return (rows_t * [1, 1, 1e6], rows_v * [1, 1, 1e6])


def external_table() -> tuple[list[str], int]:
    """The records others made (``test/external_records.py``), each judged quiet and with two busy loops beside:
    (table lines, how many are right)."""
    lines = ["| record | right | named | right? | held-out RMS [um] | peak [% of range] | fit [%] | noise floor | "
             "s quiet | s, two busy loops beside |", "|---|---|---|---|---|---|---|---|---|---|"]
    right = 0
    for name, case in external.EXTERNAL.items():
        train, validate = case.records()
        report, quiet = judge_records(train, validate)
        with busy_loops():
            loaded, seconds_loaded = judge_records(train, validate)
        ok = external.judged_right(name, report)
        right += ok
        truth = (", ".join(case.names) if case.names is not None else
                 f"RMS <= {external.MICRO_RMS_UM:g} um, peak <= {external.MICRO_PEAK_PCT:g} %, delay or lag named")
        b, f = report["baseline"]["validate"], report["final"]["validate"]
        floor = report["noise_floor"]
        lines.append(f"| {name} | {truth} | {story(report)} | {'yes' if ok else 'NO'} | {b['rms_um']:.3f} -> "
                     f"{f['rms_um']:.3f} | {b['peak_pct']:.2f} -> {f['peak_pct']:.2f} | {f['fit_pct']:.1f} | "
                     + (f"{floor['rms_um']:.4f} um from {floor['source']}" if floor["rms_um"] is not None else "none")
                     + f" | {quiet:.1f} | {seconds_loaded:.1f}"
                     + ("" if story(loaded) == story(report) else f" (named {story(loaded)})") + " |")
        print(lines[-1], flush=True)
    return lines, right


def judge_records(train: Record, validate: Record) -> tuple[dict, float]:
    started = time.monotonic()
    report = analyse(train, validate).report.to_json()
    return report, time.monotonic() - started


def main():
    keep_freed_memory()   # as valve_identify (runtime.memory)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--markdown", help="also write the tables here")
    ap.add_argument("--records", type=int, default=len(RECORDS), help="records per valve (at most 5)")
    ap.add_argument("--external-only", action="store_true", help="only the records others made")
    args = ap.parse_args()
    started = host_yardstick()   # the page's seconds with the host's speed as the bench started and ended
    ext_lines, ext_right = external_table()
    ext_summary = f"{ext_right} of {len(external.EXTERNAL)} records others made judged right."
    print(ext_summary)
    if args.external_only:
        if args.markdown:
            with open(args.markdown, "w") as fh:
                fh.write(EXTERNAL_NOTE.format(command=" ".join(sys.argv[1:])) + "\n\n"
                         + yardstick_note(started, host_yardstick()) + "\n\n" + "\n".join(ext_lines)
                         + "\n\n" + ext_summary + "\n")
        return
    records = RECORDS[:args.records]
    cases = [(name, case.names, case.need, case.judged_right, lambda seed, share, c=case: zoo_records(c, seed, share))
             for name, case in zoo.CASES.items()]
    for name, valve in battery.BATTERY.items():
        need = frozenset(valve.effects)
        cases.append((f"battery: {name}", need, need,
                      lambda given, unexplained, need=need: set(given) <= need and (need <= set(given) or unexplained),
                      lambda seed, share, v=valve: battery_records(v, seed, share)))
    lines = ["| case | right | first record: named | right? | held-out RMS [um] | s | "
             f"over {len(records)} records | same names | unexplained | right |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    totals = collections.Counter()
    for name, allowed, need, right, make in cases:
        stories, named, unexplained, rights, first = [], [], 0, 0, None
        for seed, share in records:
            report, seconds = judge(*make(seed, share))
            ok = right(report["effects_added"], report["unexplained"])
            rights += ok
            stories.append(story(report))
            named.append(names(report))
            unexplained += bool(report["unexplained"])
            if first is None:
                first = (report, seconds, ok)
        report, seconds, ok = first
        common, count = collections.Counter(named).most_common(1)[0]
        truth = (", ".join(sorted(need)) or "none") + (f" (may: {', '.join(sorted(allowed - need))})" if allowed - need else "")
        b, f = report["baseline"]["validate"], report["final"]["validate"]
        lines.append(f"| {name} | {truth} | {story(report)} | {'yes' if ok else 'NO'} | {b['rms_um']:.3f} -> "
                     f"{f['rms_um']:.3f} | {seconds:.1f} | {'; '.join(sorted(set(stories)))} | {count} of {len(stories)} "
                     f"| {unexplained} of {len(stories)} | {rights} of {len(stories)} |")
        print(lines[-1], flush=True)
        totals["cases"] += 1
        totals["right first"] += ok
        totals["stable"] += count >= len(stories) - 1
        totals["right always"] += rights == len(stories)
    summary = (f"{totals['right first']} of {totals['cases']} cases judged right on the first record; "
               f"{totals['stable']} give the same names on at least {len(records) - 1} of {len(records)} records; "
               f"{totals['right always']} are right on every record.")
    print(summary)
    if args.markdown:
        with open(args.markdown, "w") as fh:
            fh.write(EXTERNAL_NOTE.format(command=" ".join(sys.argv[1:])) + "\n\n"
                     + yardstick_note(started, host_yardstick()) + "\n\n" + "\n".join(ext_lines) + "\n\n"
                     + ext_summary + "\n\n## The zoo\n\n")
            fh.write(f"Output of `python bench/zoo.py {' '.join(sys.argv[1:])}`: held-out figures on a separate "
                     "validation session at the record's rate; each zoo valve's sessions start after an excitation "
                     "nobody recorded. 'right': the names the loop must give unless it says unexplained (and, in "
                     "brackets, may give besides). Records: seed / training length " +
                     ", ".join(f"{s} / {int(100 * sh)} %" for s, sh in records) + ".\n\n"
                     + "\n".join(lines) + "\n\n" + summary + "\n")


if __name__ == "__main__":
    main()
