"""Run by the ParaView *GUI* application (``paraview --script=this --exit``, under ``xvfb-run``):
loads the plugin, opens a model as a user's File > Open would, shows it, and writes what it got to
``$ISM_PV_RESULT`` (JSON) for ``tools/test_paraview.sh`` to check. Paths come from the environment
(``--script`` takes no arguments): ``ISM_PV_PLUGIN``, ``ISM_PV_FILE``, ``ISM_PV_RESULT``."""

import json
import os

from paraview.simple import GetActiveViewOrCreate, LoadPlugin, OpenDataFile, Render, Show

LoadPlugin(os.environ["ISM_PV_PLUGIN"], ns=globals())
reader = OpenDataFile(os.environ["ISM_PV_FILE"])
reader.UpdatePipeline()
Show(reader, GetActiveViewOrCreate("RenderView"))
Render()
info = reader.GetDataInformation()
with open(os.environ["ISM_PV_RESULT"], "w", encoding="utf-8") as f:
    json.dump({"reader": reader.GetXMLName(), "cells": info.GetNumberOfCells(), "points": info.GetNumberOfPoints()}, f)
