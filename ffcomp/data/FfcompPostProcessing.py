# Cura post-processing script for ffcomp (model-based feedforward vibration compensation).
#
# Install: copy this file into Cura's "scripts" folder (Help > Show Configuration Folder, then
# scripts/), restart Cura, and add "ffcomp vibration compensation" under Extensions > Post
# Processing > Modify G-Code.  ffcomp must be installed (pip install ffcomp) where the command
# below can find it.
import json
import os
import subprocess
import tempfile

from ..Script import Script  # provided by Cura's PostProcessingPlugin


class FfcompPostProcessing(Script):
    def getSettingDataString(self):
        return json.dumps({
            "name": "ffcomp vibration compensation",
            "key": "FfcompPostProcessing",
            "metadata": {},
            "version": 2,
            "settings": {
                "ffcomp": {"label": "ffcomp command", "description": "Path of the ffcomp executable",
                           "type": "str", "default_value": "ffcomp"},
                "profile": {"label": "Printer profile", "description": "ffcomp printer profile (TOML); "
                            "empty for the built-in default", "type": "str", "default_value": ""},
                "tol_um": {"label": "Tolerance (um)", "description": "Point placement tolerance",
                           "type": "float", "default_value": 5.0},
                "hold_margin_ms": {"label": "Rest around retractions (ms)", "description": "Rest added "
                                   "before each retraction and after each unretraction, in which the "
                                   "compensation settles and pre-actuates (0: none)",
                                   "type": "float", "default_value": 0.0},
            },
        })

    def execute(self, data):
        # Cura hands over a list of layer strings; ffcomp works on the whole file
        fd, path = tempfile.mkstemp(suffix=".gcode")
        with os.fdopen(fd, "w") as f:
            f.write("".join(data))
        cmd = [self.getSettingValueByKey("ffcomp"), "hook", path,
               "--tol-um", str(self.getSettingValueByKey("tol_um")),
               "--hold-margin-ms", str(self.getSettingValueByKey("hold_margin_ms"))]
        profile = self.getSettingValueByKey("profile")
        if profile:
            cmd += ["--profile", profile]
        try:
            subprocess.run(cmd, check=True, capture_output=True, text=True)
            with open(path) as f:
                return [f.read()]
        except subprocess.CalledProcessError as e:
            raise RuntimeError("ffcomp failed: " + (e.stderr or str(e))) from e
        finally:
            os.unlink(path)
