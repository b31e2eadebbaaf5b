"""The add-on zipped the way `make blender-addon` zips it installs as a Blender extension from disk.

It runs in a child process with its own user folder: installing enables the extension, which would
register a second copy of the add-on's classes in this session."""

import subprocess
import sys
import zipfile
from pathlib import Path

ADDON = Path(__file__).resolve().parents[1] / "blender" / "cfx_blender"

INSTALL = """
import sys
import bpy
result = bpy.ops.extensions.package_install_files(filepath=sys.argv[1], repo="user_default", enable_on_install=True)
assert result == {"FINISHED"}, result
assert "bl_ext.user_default.cfx_blender" in sys.modules
assert hasattr(bpy.types.Scene, "cfx") and bpy.types.CFX_PT_panel.bl_category == "CFX"
for name in ("simulate", "export_cache", "tag", "export_stage"):
    assert hasattr(bpy.ops.cfx, name), name
print("installed")
"""


def test_extension_zip_installs_from_disk(tmp_path):
    archive = tmp_path / "cfx_blender.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for path in [ADDON / "blender_manifest.toml", *sorted(ADDON.glob("*.py"))]:
            z.write(path, path.name)
    env = {"BLENDER_USER_RESOURCES": str(tmp_path / "user"), "PATH": "/usr/bin:/bin"}
    result = subprocess.run([sys.executable, "-c", INSTALL, str(archive)], check=False, capture_output=True,
                            text=True, env=env, timeout=300)
    assert result.returncode == 0 and "installed" in result.stdout, result.stdout[-2000:] + result.stderr[-2000:]
