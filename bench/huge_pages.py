#!/usr/bin/env python3
"""The diagnosis alone with numpy's huge-page advice and without it (``heap_policy.small_pages_for_arrays``).

numpy advises the kernel to back each of its arrays of 4 MiB or more with transparent huge pages; the diagnosing
process's heap policy turns that advice off. This runs the diagnosis alone (``bench/diagnose_command.py
--diagnosis-alone``, one lane) on the simulator's benchmark run of N samples (``floors.diagnose_files``) in child
processes, alternately with the advice left on (``--numpy-huge-pages``) and as the policy sets it, and prints the
median CPU time (user + system), system time and peak RSS of each, and the median of the per-pair CPU ratios. The
advice matters only where ``/sys/kernel/mm/transparent_hugepage/enabled`` is ``madvise`` (printed).

    .venv/bin/python bench/huge_pages.py --pairs 5 --dir /tmp/bench   # 10^6 samples, the files kept for later runs
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from floors import diagnose_files, interleaved, made_in_a_child
from machine_info import results_doc, write_results
from output_paths import results_dir

HERE = Path(__file__).resolve().parent
THP = Path("/sys/kernel/mm/transparent_hugepage")


def kernel_setting(name: str) -> str:
    """The kernel's transparent huge page setting ``name`` (``enabled``, ``defrag``), or "unknown"."""
    try:
        return (THP / name).read_text().strip()
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=float, default=1e6, help="samples of the diagnosed run (default 10^6)")
    ap.add_argument("--pairs", type=int, default=5, help="alternated pairs (default %(default)s)")
    ap.add_argument("--dir", type=Path, default=None, help="keep the run's files here (reused by later runs)")
    args = ap.parse_args(argv)
    n = int(args.samples)
    doc = results_doc("huge_pages.py", argv, benchmark="huge_pages",
                      transparent_hugepage={k: kernel_setting(k) for k in ("enabled", "defrag")})
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.dir or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        made_in_a_child("diagnose", n, folder)
        path, _ = diagnose_files(n, folder)
        alone = [sys.executable, str(HERE / "diagnose_command.py"), "--diagnosis-alone", str(path), "--lanes", "1"]
        res = interleaved([*alone, "--numpy-huge-pages"], alone, args.pairs)
    with_advice, without = res["floor"], res["project"]
    doc.update(samples=n, with_advice=with_advice, without_advice=without, cpu_ratio=res["cpu_ratio"],
               cpu_ratio_range=res["cpu_ratio_range"], pairs=args.pairs)
    print(f"transparent huge pages: enabled {doc['transparent_hugepage']['enabled']}, "
          f"defrag {doc['transparent_hugepage']['defrag']}")
    for name, r in (("with numpy's advice", with_advice), ("without it (the policy)", without)):
        print(f"{name}: CPU {r['cpu_s']:.2f} s (system {r['sys_s']:.2f} s), peak RSS {r['rss_mib']:.0f} MiB")
    print(f"without / with: {res['cpu_ratio']:.3f} (pairs {res['cpu_ratio_range'][0]}-{res['cpu_ratio_range'][1]})")
    out = results_dir(False) / "huge_pages.json"
    write_results(out, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
