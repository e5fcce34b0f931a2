"""Progress bars of the client commands (tqdm, on stderr): a job's 0-100 progress with its stage, and bytes."""

from __future__ import annotations

import sys

from tqdm import tqdm


class JobBar:
    """A bar over the job's ``progress`` (0-100, never decreasing on the server), captioned with the stage and
    its message. Call it with every polled status."""

    def __init__(self, job_id: str, disable: bool | None = None) -> None:
        self.job_id = job_id
        self.bar = tqdm(total=100.0, unit="%", file=sys.stderr, dynamic_ncols=True, disable=disable,
                        bar_format="{desc}: {percentage:5.1f}%|{bar}| [{elapsed}{postfix}]")
        self.bar.set_description_str(job_id)
        self.last: tuple[str, str | None] | None = None

    def __call__(self, job: dict) -> None:
        if self.bar.disable:  # not a terminal (a log file, CI): one line per stage or state change instead
            seen = (job["state"], job.get("stage"))
            if seen != self.last:
                self.last = seen
                pct = float(job.get("progress") or 0.0)
                sys.stderr.write(f"{self.job_id}: {job['state']} {job.get('stage') or '-'} {pct:.1f} %\n")
                sys.stderr.flush()
            return
        self.bar.n = min(100.0, float(job.get("progress") or 0.0))
        stage = job.get("stage") or "-"
        self.bar.set_description_str(f"{self.job_id} {job['state']} {stage}", refresh=False)
        self.bar.set_postfix_str((job.get("message") or "")[:60], refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def byte_bar(total: int, what: str, disable: bool | None = None) -> tqdm:
    return tqdm(total=total, unit="B", unit_scale=True, unit_divisor=1024, desc=what, file=sys.stderr,
                dynamic_ncols=True, disable=disable)
