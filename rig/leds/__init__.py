"""LED panels and trigger pulses over serial: the framed ASCII controller, DMX512 through an
Enttec DMX USB Pro-compatible interface, and a simulated controller on a pseudo-terminal.

    from rig.leds import open_led_controller
    with open_led_controller(rig.leds) as leds:
        leds.on()
        leds.flash(50)
        take["led_log"] = leds.records()

The protocol a lab's firmware implements is specified in docs/leds-protocol.md; each opened
ASCII controller is a session of its own (HELLO), so separate processes never get each other's
replies.
"""

from __future__ import annotations

from typing import Any

from manus_core.errors import LedDisconnected, LedError, LedRejected, LedStaleReply, LedTimeout, LedValueError
from manus_core.rig_config import LedConfig

from .ascii import AsciiLedController
from .base import Backoff, LedController, now_ns
from .dmx import DmxLedController
from .sim import SimulatedLedController

__all__ = ["AsciiLedController", "Backoff", "DmxLedController", "LedController", "LedDisconnected",
           "LedError", "LedRejected", "LedStaleReply", "LedTimeout", "LedValueError", "SimulatedLedController",
           "now_ns", "open_led_controller"]


def open_led_controller(cfg: LedConfig, **options: Any) -> LedController:
    """The controller rig.toml's [leds] table describes, opened and ready.

    protocol "ascii" and "dmx" open `cfg.port`; "sim" starts a SimulatedLedController on a
    pseudo-terminal, talks to it through the same ASCII client, and exposes it as `.sim`
    (closed with the controller). `options` go to the controller (timeout_s, retries, backoff, opener).
    """
    if cfg.protocol == "dmx":
        return DmxLedController(cfg.port, cfg.panels, cfg.baudrate, cfg.level, **options)
    if cfg.protocol == "ascii":
        return AsciiLedController(cfg.port, cfg.panels, cfg.baudrate, cfg.level, **options)
    if cfg.protocol == "sim":
        sim = SimulatedLedController(cfg.panels)
        try:
            controller = AsciiLedController(sim.path, cfg.panels, cfg.baudrate, cfg.level, **options)
        except BaseException:
            sim.close()
            raise
        controller.own(sim)
        controller.sim = sim
        return controller
    raise LedValueError(f"unknown LED protocol {cfg.protocol!r} (known: ascii, dmx, sim)")
