"""pyserial URL handler for ``hexsim://`` (see :mod:`fringecal.hexapod.simulator`).

Registered by ``serial.protocol_handler_packages.append("fringecal.hexapod")``, done
when :mod:`fringecal.hexapod` is imported; then ``serial.serial_for_url("hexsim://...")``
returns this port. Replies are produced synchronously when a command line is written,
so ``read`` never blocks: an empty read means the box will not answer (a timeout).
The port exposes the box's ``clock()`` and ``sleep()``, which the driver uses for its
polling and watchdogs, so with the default virtual clock a simulated move takes no
wall time.
"""

from __future__ import annotations

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from fringecal.hexapod.protocol import TERMINATOR
from fringecal.hexapod.simulator import SimulatedController, controller_for_url

__all__ = ["Serial"]


class Serial(SerialBase):
    """A serial port wired to a :class:`SimulatedController`."""

    def __init__(self, *args, **kwargs):
        self.controller: SimulatedController | None = None
        self._rx = bytearray()
        self._tx = bytearray()
        super().__init__(*args, **kwargs)

    def open(self):
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        try:
            box = controller_for_url(self._port)
        except ValueError as err:
            raise SerialException(str(err)) from None
        if box.fault == "unplugged":
            raise SerialException(f"could not open port {self._port}: no such device (simulated unplugged cable)")
        self.controller = box
        self._rx.clear()
        self._tx.clear()
        self.is_open = True

    def close(self):
        self.is_open = False
        super().close()

    def _reconfigure_port(self):
        pass

    def _check(self):
        if not self.is_open:
            raise PortNotOpenError()
        if self.controller.fault == "disconnect" and self.controller.n_received > self.controller.fault_after:
            raise SerialException(f"{self._port}: device disconnected (simulated)")

    def write(self, data):
        self._check()
        data = bytes(data)
        self._tx += data
        while TERMINATOR in self._tx:
            i = self._tx.index(TERMINATOR) + 1
            line, self._tx = bytes(self._tx[:i]), self._tx[i:]
            reply = self.controller.handle(line)
            if reply:
                self._rx += reply
        return len(data)

    def read(self, size=1):
        self._check()
        out, self._rx = bytes(self._rx[:size]), self._rx[size:]
        return out

    @property
    def in_waiting(self):
        self._check()
        return len(self._rx)

    def reset_input_buffer(self):
        self._check()
        self._rx.clear()

    def reset_output_buffer(self):
        self._check()
        self._tx.clear()

    # time source of the simulated box (used by the driver's polling and watchdogs)
    def clock(self) -> float:
        return self.controller.now()

    def sleep(self, seconds: float) -> None:
        self.controller.sleep(seconds)
