"""A misbehaving third-party SSM for the fault tests (installed on the fly by
``tests/test_plugin_faults.py``): ``toy-faulty`` grows the toy tree, but misbehaves on the points
whose angle lies above ``fault_above``, in the way ``fault`` names: ``exit`` (sys.exit),
``abort`` (os.abort), ``segv`` (a segfault through ctypes), ``attribute`` (AttributeError),
``own`` (an exception class of its own), ``none`` (returns None), ``unpicklable`` (an exception
that cannot be pickled), ``keyboard`` (a KeyboardInterrupt of its own), ``base`` (a bare
BaseException subclass) or ``c-block`` (blocks in C holding the interpreter lock, deaf to alarms).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from pathlib import Path
from typing import Literal

from bforest_toy import ToySSM, ToySSMSettings
from pydantic import Field

from bforest_core.hookspecs import hookimpl

FAULTS = ("exit", "abort", "segv", "attribute", "own", "none", "unpicklable", "keyboard", "base", "c-block")


class ToyModelError(Exception):
    """The plugin's own exception class."""


class ToyBaseFault(BaseException):
    """Not an Exception: what ``except Exception`` lets through."""


class Unpicklable(Exception):
    def __init__(self, message):
        super().__init__(message)
        self.callback = lambda: None  # a lambda cannot be pickled


class FaultySettings(ToySSMSettings):
    fault: Literal[FAULTS] = Field("segv", description="how the model misbehaves")
    fault_above: float = Field(1e9, description="misbehave when angle exceeds this")
    pid_dir: str = Field("", description="a folder where each simulating process leaves a file named by its pid")


class FaultySSM(ToySSM):
    name = "toy-faulty"
    summary = "toy model that misbehaves on purpose (tests)"
    Settings = FaultySettings

    def simulate(self, params, seed):
        s = self.settings
        if s.pid_dir:
            Path(s.pid_dir, str(os.getpid())).touch()
        if self.resolve_params(params)["angle"] > s.fault_above:
            if s.fault == "exit":
                sys.exit(3)
            if s.fault == "abort":
                os.abort()
            if s.fault == "segv":
                ctypes.string_at(0)
            if s.fault == "attribute":
                raise AttributeError("'Bud' object has no attribute 'children'")
            if s.fault == "own":
                raise ToyModelError("the growth stalled")
            if s.fault == "none":
                return None
            if s.fault == "unpicklable":
                raise Unpicklable("cannot travel")
            if s.fault == "keyboard":
                raise KeyboardInterrupt("the plugin's own")
            if s.fault == "base":
                raise ToyBaseFault("below Exception")
            if s.fault == "c-block":
                signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
                ctypes.PyDLL(None).sleep(600)  # in C, holding the interpreter lock
        return super().simulate(params, seed)


@hookimpl
def bforest_components():
    return [FaultySSM]
