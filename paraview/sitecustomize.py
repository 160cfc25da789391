"""Put on ParaView's Python path (``tools/test_paraview.sh`` copies it beside the ``ism`` package):
Python imports ``sitecustomize`` at start-up, before ParaView loads any Python plugin.

ParaView 5.11's ``paraview.detail.pythonalgorithm`` (imported by the plugin loader itself, before
a plugin's own code runs) does ``from inspect import getargspec``, which Python 3.11 removed.
``getfullargspec`` returns the same leading fields (args, varargs, varkw, defaults), the ones it
reads. On a Python that still has ``getargspec`` nothing is changed.

This shadows the system's ``sitecustomize`` (Debian's installs an apport hook); that one is run
afterwards, so nothing it does is lost.
"""

import inspect
import os
import sys

if not hasattr(inspect, "getargspec"):
    inspect.getargspec = inspect.getfullargspec

_here = os.path.dirname(os.path.abspath(__file__))
for _dir in sys.path:
    _candidate = os.path.join(_dir or ".", "sitecustomize.py")
    if os.path.abspath(_dir or ".") != _here and os.path.isfile(_candidate):
        with open(_candidate, encoding="utf-8") as _f:
            exec(compile(_f.read(), _candidate, "exec"), {"__name__": "sitecustomize", "__file__": _candidate})
        break
