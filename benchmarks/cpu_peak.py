"""The CPU's peak floating-point rate: what no kernel on this machine can beat.

A tiny C program (compiled here with the system's C compiler) runs 16
(AVX-512) or 12 (AVX2) independent chains of fused multiply-adds per
thread, enough to keep every FMA pipe busy, with no memory traffic: float32
FMAs on 512-bit registers (AVX-512) or 256-bit ones (AVX2), and, where the
CPU has AVX512-BF16, the
bfloat16 dot-product instruction (``vdpbf16ps``: bf16 pairs, float32
accumulation, what a bfloat16-input matmul runs on). One run per thread count
from 1 to ``os.cpu_count()``, medians over ``--repeats`` runs.

    python benchmarks/cpu_peak.py            # JSON line at the end

``benchmarks/gnn.py`` reports the same peak next to its steps
(``fma_peak_gflops_per_s``, ``rollout_step_ms_at_fma_peak``): a step's
dense-layer FLOPs divided by the peak is the time the step cannot go below on
this machine, whatever the software.

x86-64 only (other CPUs, or no C compiler: :func:`fma_peak` returns ``None``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from _machine import machine_info

_SOURCE = r"""
#include <immintrin.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

/* Independent accumulators per thread, more than FMA latency x pipes, and
   with the two operands still within the register file (32 zmm, 16 ymm). */
#if defined(WIDE)
typedef __m512 vec;
#define SET1 _mm512_set1_ps
#define FMA _mm512_fmadd_ps
#define LANES 16
#define CHAINS 16
#else
typedef __m256 vec;
#define SET1 _mm256_set1_ps
#define FMA _mm256_fmadd_ps
#define LANES 8
#define CHAINS 12
#endif
static long iterations;
static int kind;
static volatile float sink[256];

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

static float lane_sum(vec v) {
  float lanes[LANES], total = 0.0f;
  memcpy(lanes, &v, sizeof v);
  for (int k = 0; k < LANES; k++) total += lanes[k];
  return total;
}

static void *work(void *arg) {
  int id = (int)(long)arg;
  float total = 0.0f;
  vec acc[CHAINS];
  if (kind == 0) {
    vec b = SET1(0.999f), c = SET1(1e-7f);
    for (int i = 0; i < CHAINS; i++) acc[i] = SET1(1.0f + i);
    for (long n = 0; n < iterations; n++) {
#pragma GCC unroll 16
      for (int i = 0; i < CHAINS; i++) acc[i] = FMA(acc[i], b, c);
    }
  }
#if defined(BF16)
  if (kind == 1) {
    __m512bh x = (__m512bh)_mm512_set1_epi16(0x3f80), y = (__m512bh)_mm512_set1_epi16(0x3400);
    for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_setzero_ps();
    for (long n = 0; n < iterations; n++) {
#pragma GCC unroll 16
      for (int i = 0; i < CHAINS; i++) acc[i] = _mm512_dpbf16_ps(acc[i], x, y);
    }
  }
#endif
  for (int i = 0; i < CHAINS; i++) total += lane_sum(acc[i]);
  sink[id % 256] = total;
  return 0;
}

int main(int argc, char **argv) {
  int threads = atoi(argv[1]);
  kind = atoi(argv[2]);
  iterations = atol(argv[3]);
  pthread_t t[256];
  double start = now();
  for (int i = 0; i < threads; i++) pthread_create(&t[i], 0, work, (void *)(long)i);
  for (int i = 0; i < threads; i++) pthread_join(t[i], 0);
  printf("%.9f\n", now() - start);
  return 0;
}
"""


def _cpu_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            line = next(line for line in f if line.startswith("flags"))
        return set(line.split(":", 1)[1].split())
    except (OSError, StopIteration):
        return set()


class _Kernel:
    """The compiled program and what it can measure on this CPU."""

    def __init__(self, directory: Path):
        flags = _cpu_flags()
        self.wide = "avx512f" in flags
        self.bf16 = self.wide and "avx512_bf16" in flags
        if not self.wide and not {"avx2", "fma"} <= flags:
            raise RuntimeError("neither AVX-512 nor AVX2+FMA on this CPU")
        compiler = shutil.which(os.environ.get("CC", "cc")) or shutil.which("gcc")
        if compiler is None:
            raise RuntimeError("no C compiler (set CC)")
        source, self.binary = directory / "peak.c", directory / "peak"
        source.write_text(_SOURCE)
        if self.wide:
            isa = ["-mavx512f", "-DWIDE"] + (["-mavx512bf16", "-DBF16"] if self.bf16 else [])
        else:
            isa = ["-mavx2", "-mfma"]
        subprocess.run(
            [compiler, "-O2", *isa, "-pthread", str(source), "-o", str(self.binary)],
            check=True,
            capture_output=True,
            text=True,
        )

    def flop_per_iteration(self, bf16: bool) -> float:
        lanes, chains = (16, 16) if self.wide else (8, 12)
        # An FMA is 2 FLOPs per float32 lane; vdpbf16ps does 2 bf16 products per lane and adds them.
        return chains * lanes * (4.0 if bf16 else 2.0)

    def rate(self, threads: int, bf16: bool, seconds: float = 0.3) -> float:
        """GFLOP/s of one run of ``threads`` threads lasting about ``seconds``."""
        iterations = 1_000_000
        while True:
            out = subprocess.run(
                [str(self.binary), str(threads), "1" if bf16 else "0", str(iterations)],
                check=True,
                capture_output=True,
                text=True,
            )
            wall = float(out.stdout)
            if wall >= seconds / 3:
                return threads * self.flop_per_iteration(bf16) * iterations / wall / 1e9
            iterations = int(iterations * max(2.0, seconds / max(wall, 1e-6)))


def fma_peak(threads: int | None = None, repeats: int = 5) -> dict | None:
    """Median peak GFLOP/s with ``threads`` threads (default: every core), or ``None`` if it cannot be measured.

    Returns ``{"float32": GFLOP/s, "bfloat16": GFLOP/s or None, "isa":
    "avx512" | "avx2", "threads": int}``.
    """
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return None
    threads = (os.cpu_count() or 1) if threads is None else threads
    with tempfile.TemporaryDirectory(prefix="dispgns-peak-") as tmp:
        try:
            kernel = _Kernel(Path(tmp))
        except (RuntimeError, subprocess.CalledProcessError):
            return None
        f32 = float(np.median([kernel.rate(threads, False) for _ in range(repeats)]))
        bf16 = float(np.median([kernel.rate(threads, True) for _ in range(repeats)])) if kernel.bf16 else None
        return {"float32": f32, "bfloat16": bf16, "isa": "avx512" if kernel.wide else "avx2", "threads": threads}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per thread count (median)")
    args = parser.parse_args()
    report = machine_info()
    for threads in range(1, (os.cpu_count() or 1) + 1):
        peak = fma_peak(threads, args.repeats)
        if peak is None:
            raise SystemExit(
                "cannot measure the FMA peak here (needs x86-64 with AVX2+FMA or AVX-512, and a C compiler: set CC)"
            )
        report["isa"] = peak["isa"]
        report[f"float32_gflops_per_s_{threads}_threads"] = peak["float32"]
        report[f"bfloat16_gflops_per_s_{threads}_threads"] = peak["bfloat16"]
        print(
            f"{threads} thread(s): float32 {peak['float32']:.0f} GFLOP/s"
            + ("" if peak["bfloat16"] is None else f", bfloat16 dot {peak['bfloat16']:.0f} GFLOP/s"),
            flush=True,
        )
    print(json.dumps(report))


if __name__ == "__main__":
    main()
