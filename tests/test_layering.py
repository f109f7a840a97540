"""The math never imports the transport (STYLE.md 1): checked in a fresh interpreter."""
import subprocess
import sys

MATH = ["eonav.geometry", "eonav.camera", "eonav.pairfile", "eonav.locate", "eonav.rangemap", "eonav.schema",
        "eonav.keys", "eonav.imageio", "eonav.fusion", "eonav.fusion.state", "eonav.fusion.predict",
        "eonav.fusion.update", "eonav.fusion.fused_map", "eonav.fusion.schedule", "eonav.fusion.sequence",
        "eonav.sim.sequence"]


def test_math_modules_do_not_load_zenoh():
    code = "import sys\n" + "".join(f"import {m}\n" for m in MATH) + "print('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_fusion_modules_do_not_load_the_transport_or_mavlink():
    code = ("import sys\n" + "".join(f"import {m}\n" for m in MATH if "fusion" in m)
            + "import eonav.fusion._kernels\nprint(sorted(m for m in ('zenoh', 'pymavlink') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_cli_help_is_light():
    code = "import sys\nfrom eonav.cli import build_parser\nbuild_parser()\nprint(sorted(m for m in ('zenoh', 'cv2', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
