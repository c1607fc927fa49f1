"""Benchmark EDI (issue 15, item 2): one 40 ms batch at 240×180 with 50–200 k events.

The events are synthetic but shaped like a busy DAVIS240C batch: 80 % of them on a band of
"edge" pixels (20 % of the array), the rest spread as background activity, both polarities,
sorted by time. For each count it times, on this machine (best of a few runs):

* building the per-pixel index (:class:`EdiBatch`),
* one sharp frame of a 10 ms exposure (:meth:`EdiBatch.deblur`),
* 41 latent images, one per ms of the batch (:meth:`EdiBatch.latent_log_images`),
* Pan et al.'s criterion for c (:meth:`EdiBatch.estimate_contrast`, 17-point grid + refine),
* the two-frame fit of c (:meth:`EdiBatch.fit_contrast`).

Prints one JSON object as its last line. Run: ``.venv/bin/python benchmarks/eventcap_edi.py``.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable

import numpy as np

from mocaprig.acquire.events import make_events
from mocaprig.process.eventcap.edi import ContrastEstimate, EdiBatch, SharpFrame

_H, _W = 180, 240
_T_US = 40_000


def best_of(fn: Callable[[], object], *, repeat: int = 3) -> float:
    """Minimum wall time of ``repeat`` calls (s)."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def synthetic_batch(n: int, seed: int) -> np.ndarray:
    """``n`` events in [0, 40 ms], 80 % on 20 % of the pixels (module doc)."""
    rng = np.random.default_rng(seed)
    busy = rng.choice(_H * _W, size=_H * _W // 5, replace=False)
    n_edge = int(0.8 * n)
    pix = np.concatenate([rng.choice(busy, n_edge), rng.integers(0, _H * _W, n - n_edge)])
    t = np.sort(rng.integers(0, _T_US + 1, n))
    return make_events(t, pix % _W, pix // _W, rng.random(n) < 0.5)


def time_count(n: int, frame_a: np.ndarray, frame_b: np.ndarray) -> dict[str, float]:
    """Timings (s) of one 40 ms batch of ``n`` events (module doc)."""
    ev = synthetic_batch(n, seed=n)
    exp_a, exp_b = (0, 10_000), (30_000, 40_000)

    def build() -> EdiBatch:
        return EdiBatch(ev, shape_hw=(_H, _W), t_start_us=0, t_end_us=_T_US)

    batch = build()

    def deblur() -> SharpFrame:
        return batch.deblur(
            frame_a, exposure_start_us=exp_a[0], exposure_end_us=exp_a[1], c_on=0.2, c_off=0.2
        )

    sharp = deblur()

    def latents() -> np.ndarray:
        return batch.latent_log_images(sharp, np.arange(0, _T_US + 1, 1000))

    def criterion() -> ContrastEstimate:
        return batch.estimate_contrast(
            frame_a, exposure_start_us=exp_a[0], exposure_end_us=exp_a[1]
        )

    def pair_fit() -> ContrastEstimate:
        return batch.fit_contrast(frame_a, frame_b, exposure_a_us=exp_a, exposure_b_us=exp_b)

    return {
        "build_s": best_of(build),
        "deblur_10ms_s": best_of(deblur),
        "latent_41_s": best_of(latents),
        "estimate_contrast_s": best_of(criterion, repeat=1),
        "fit_contrast_s": best_of(pair_fit, repeat=1),
    }


def main() -> None:
    rng = np.random.default_rng(0)
    frame_a = rng.uniform(20.0, 900.0, (_H, _W))
    frame_b = rng.uniform(20.0, 900.0, (_H, _W))
    results: dict[str, object] = {"machine": platform.processor() or platform.machine()}
    for n in (50_000, 100_000, 200_000):
        row = time_count(n, frame_a, frame_b)
        results[f"{n}_events"] = {k: round(v, 4) for k, v in row.items()}
        print(n, results[f"{n}_events"])
    print(json.dumps(results))


if __name__ == "__main__":
    main()
