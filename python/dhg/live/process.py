"""``dhg-serve`` as a child process: what ``dhg live-demo``, the end-to-end tests and the
benchmark scripts start a server with. The server is the product's own command, run as a user runs
it; this class only waits for its ready line, keeps its output and stops it as Ctrl-C would."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading

from dhg.core.errors import TransportError

__all__ = ["ServerProcess", "free_port"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """``dhg-serve`` as a child process; its output lines are echoed (with ``echo``) and kept."""

    def __init__(self, args: list[str], echo: bool = True, ready_timeout_s: float = 120.0):
        self.lines: list[str] = []
        self._ready: queue.Queue[str] = queue.Queue()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dhg.cli.serve", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self._echo = echo
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        try:
            line = self._ready.get(timeout=ready_timeout_s)
        except queue.Empty:
            self.stop()
            raise TransportError(f"dhg-serve was not ready within {ready_timeout_s} s") from None
        if not line.startswith("dhg-serve ready"):
            self.stop()
            raise TransportError("dhg-serve did not start:\n" + "\n".join(self.lines[-10:]))

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            if self._echo:
                print(f"  server │ {line}", flush=True)
            if line.startswith("dhg-serve ready"):
                self._ready.put(line)
        self._ready.put("exited")

    def stop(self, timeout_s: float = 20.0) -> int:
        """SIGTERM, then wait; SIGKILL if it does not stop in time. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(timeout=5.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return int(self.proc.returncode)
