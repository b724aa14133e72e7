"""The one exception type for user mistakes.

Anything a user can cause (a malformed dataset, a bad config key, an unknown method) raises
`DegustaError` with a message that names the file, line, field or key. The CLI prints that message on
one line and exits 2 (degusta_learn/cli.py lists every exit code); every other exception is a bug and keeps
its traceback.
"""


class DegustaError(Exception):
    """A user-facing error: the message alone must say what is wrong and where."""


class MachineMismatch(DegustaError):
    """A valid config that this machine cannot run: no GPU for a GPU config, too few devices, a logger package
    not installed, a multi-node run not started by a launcher. `train --dry-run` reports it as a check that FAILS,
    prints the rest of the report and exits 3 (a GPU config checked on a login node: the report holds, this machine
    cannot run it); a config mistake (`DegustaError`) fails the dry run like the real one (exit 2)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's kill, `timeout`, `kill PID`), raised in the main thread as Ctrl-C is, so every
    path that keeps finished work on Ctrl-C (caches, ledgers, staged folders) keeps it on SIGTERM too; the CLI
    exits 128 + the signal number (143)."""

    def __init__(self, signum: int = 15):
        super().__init__(f"signal {signum}")
        self.signum = signum
