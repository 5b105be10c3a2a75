"""``pmask view ARTIFACT``: the model in a browser, with the mouse as a haptic probe.

A local HTTP server (the standard library's, on 127.0.0.1 unless ``--host`` says otherwise) serves one
page and a small JSON API; the haptic step runs on the server, in the servo core's own 1 kHz thread
(:meth:`pmask.runtime.Contacts.start`), exactly the step a device would get, and the page sets the
probes and reads forces, states and the deformation (eq. 16) about 30-60 times a second.  The page is
three.js, bundled from the npm registry into ``static/viewer.bundle.js`` when the package is built
(``viewer/package.json``, ``setup.py``): nothing is fetched at run time.

Imports the runtime only (numpy, h5py and the standard library), so the viewer works with the runtime
installed alone.
"""
from pmask.viewer.server import ViewerError, ViewerSession, serve

__all__ = ["ViewerError", "ViewerSession", "serve"]
