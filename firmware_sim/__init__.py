"""firmware_sim: the virtual IMU device of slipest (hardware-in-the-loop without hardware).

It streams the stick-slip model's samples in real time over a serial link or
a CAN bus, with slipest's wire formats, and injects faults on demand.  It
uses slipest's physics and wire formats; slipest never imports it.

Modules: :mod:`~firmware_sim.device` (pacing), :mod:`~firmware_sim.link` (the
:class:`~firmware_sim.link.Link` contract), :mod:`~firmware_sim.serial_link`,
:mod:`~firmware_sim.can_link`, :mod:`~firmware_sim.faults`, :mod:`~firmware_sim.cli`.
"""
