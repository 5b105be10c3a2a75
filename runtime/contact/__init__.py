r"""The contact algorithm, one module per step (the native core in ``runtime/servo/core/`` has one C file per
step, the same code operation for operation).  :class:`pmask.runtime.Contacts` runs them each tick:

1. :mod:`~pmask.runtime.contact.tracking`: the probe's projection on the surface and the proxy that follows it;
2. :mod:`~pmask.runtime.contact.law`: the contact law (normal stiffness, friction) at the proxy;
3. :mod:`~pmask.runtime.contact.coupling`: several contacts solved together through the Green's functions;
4. :mod:`~pmask.runtime.contact.output`: the zero-order hold's error, damping and the passivity controller.

:mod:`~pmask.runtime.contact.surface` holds what the steps read (:class:`ContactSurface`, also what a runtime
table stores) and :mod:`~pmask.runtime.contact.state` what a contact keeps between ticks.
"""
from pmask.runtime.contact.state import ContactState, Status
from pmask.runtime.contact.surface import ContactSurface

__all__ = ["ContactState", "ContactSurface", "Status"]
