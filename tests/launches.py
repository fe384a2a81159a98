"""Which device each Warp kernel launch ran on: the device fixture (conftest.py) checks with it that a test on
a device launched nothing elsewhere (a code path that dropped its ``device`` argument)."""

from __future__ import annotations

import warp as wp


class LaunchRecorder:
    """Within ``with``: every ``wp.launch`` (which ``kernels.parallel.launch`` calls), recorded as
    ``seen[device name] = {kernel keys}``."""

    def __init__(self) -> None:
        self.seen: dict[str, set[str]] = {}
        self._real = None

    def __enter__(self) -> LaunchRecorder:
        self._real = real = wp.launch

        def launch(kernel, *args, **kw):
            dev = kw.get("device", args[5] if len(args) > 5 else None)
            self.seen.setdefault(str(wp.get_device(dev)), set()).add(getattr(kernel, "key", str(kernel)))
            return real(kernel, *args, **kw)

        wp.launch = launch
        return self

    def __exit__(self, *exc) -> None:
        wp.launch = self._real

    def elsewhere(self, device: str) -> dict[str, list[str]]:
        """The kernels launched on a device other than ``device`` ("cpu", "cuda:0"), by device."""
        return {d: sorted(k) for d, k in self.seen.items() if d != device}
