"""Reach the Blender layer from the command line without importing ``bpy`` in the core.

``ssm build`` writes ``model.blend`` and the mode pictures when the ``bpy`` module is
importable and the Blender layer (the extension's ``operators`` package) can be found:
inside Blender the extension passes its writer itself (``operators/cli.py``); from a
source checkout the extension root next to this package is loaded as the package
``ssm``. The operators import the core as ``ssm_addon``, so the core exists once.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from ..base.errors import SSMError
from ..pipeline.joint import JointStudy
from ..pipeline.store import load_study_or_joint, save_joint_study, save_study

PACKAGE_NAME = "ssm"

#: What Blender's offscreen GPU set-up prints on machines without a display although it draws:
#: not an error a user can act on.
EGL_NOISE = re.compile(r"^EGL Error \(0x[0-9A-Fa-f]+\): ")
#: Lines Blender itself prints when it writes a file (its render log and its save note): not the build's.
BLENDER_NOTES = re.compile(r"^((\d\d:)?\d\d:\d\d\.\d+\s+render\s+\| Saved: |Info: Saved copy as )")


def bpy_available() -> bool:
    """True when the ``bpy`` module can be imported (Blender or ``pip install bpy``)."""
    return "bpy" in sys.modules or importlib.util.find_spec("bpy") is not None


def extension_root() -> Path | None:
    """The extension folder of a source checkout (holding this core), or None."""
    root = Path(__file__).resolve().parents[2]
    if (root / "blender_manifest.toml").is_file() and (root / "operators" / "__init__.py").is_file():
        return root
    return None


def extension_package():
    """The extension package (the checkout's root imported as ``ssm``), or None."""
    root = extension_root()
    if root is None:
        return None
    module = sys.modules.get(PACKAGE_NAME)
    if module is not None and Path(getattr(module, "__file__", "") or "").resolve() == root / "__init__.py":
        return module
    spec = importlib.util.spec_from_file_location(PACKAGE_NAME, root / "__init__.py",
                                                  submodule_search_locations=[str(root)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[PACKAGE_NAME] = module
    spec.loader.exec_module(module)
    return module


def blend_writer():
    """``write_build_outputs(study, output, out_dir, log)`` of the Blender layer (``study``: a
    :class:`~ssm_addon.pipeline.study.Study` or a :class:`~ssm_addon.pipeline.joint.JointStudy`), or None."""
    if not bpy_available():
        return None
    pkg = extension_package()
    if pkg is None:
        return None
    return importlib.import_module(f"{pkg.__name__}.operators.project").write_build_outputs


def blend_writer_in_child():
    """Like :func:`blend_writer`, but the Blender step runs in its own process and session.

    The study (or joint study) is handed over on disk (:mod:`ssm_addon.pipeline.store`: arrays
    and JSON, no pickles). A signal (Ctrl-C, SIGTERM, SIGHUP) reaches only this process, which stops
    the child and cleans up: it cannot interrupt Blender's C code half-way (that
    segfaulted). Returns None when the Blender layer is not available.
    """
    if not bpy_available() or extension_root() is None:
        return None

    def write(study, output, out_dir, log=print):

        out_dir = Path(out_dir)
        handover = Path(tempfile.mkdtemp(prefix="ssm-blender-step-"))
        try:
            given = dataclasses.replace(study, params=study.params.replace(output=output))
            (save_joint_study if isinstance(study, JointStudy) else save_study)(given, handover)
            cmd = [sys.executable, "-m", "ssm_addon.cli.blender_layer", str(handover), str(out_dir)]
            if log is None:
                cmd.append("--quiet")
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(
                filter(None, [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH")]))}
            child = subprocess.Popen(cmd, start_new_session=True, env=env, stderr=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, errors="replace")
            said: list[str] = []
            reader = threading.Thread(target=lambda: said.extend(child.stderr), daemon=True)
            reader.start()

            def relay():  # the step's own lines go on; Blender's file notes ("Saved: …") are not the build's
                for line in child.stdout:
                    if not BLENDER_NOTES.match(line):
                        sys.stdout.write(line)
                        sys.stdout.flush()

            relayer = threading.Thread(target=relay, daemon=True)
            relayer.start()
            try:
                while child.poll() is None:
                    try:
                        child.wait(0.1)
                    except subprocess.TimeoutExpired:
                        pass
                reader.join(10.0)
                relayer.join(10.0)
            except BaseException:
                child.terminate()
                try:
                    child.wait(1.0)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait()
                raise
        finally:
            shutil.rmtree(handover, ignore_errors=True)
        # Blender's offscreen GPU set-up says "EGL Error (0x3009): EGL_BAD_MATCH …" while the pictures are
        # drawn all the same: not shown when the step succeeded; everything it said is shown when it failed
        shown = said if child.returncode != 0 else [ln for ln in said if not (EGL_NOISE.match(ln)
                                                                              or BLENDER_NOTES.match(ln))]
        sys.stderr.write("".join(shown))
        if child.returncode != 0:
            raise SSMError(f"the Blender step (model.blend, modes.png) failed in its process (exit "
                           f"{child.returncode}); rerun with --no-blend to build without it")
        return {key: name for key, name in (("picture", "modes.png"), ("blend", "model.blend"))
                if (out_dir / name).is_file()}

    return write


def _child_main(argv) -> int:
    """``python -m ssm_addon.cli.blender_layer STUDY_DIR OUT_DIR [--quiet]``: the Blender step."""
    study, _extra = load_study_or_joint(argv[0])
    writer = blend_writer()
    if writer is None:
        print("the Blender layer is not available", file=sys.stderr)
        return 2
    writer(study, study.params.output, Path(argv[1]), log=None if "--quiet" in argv else (lambda m: print(m, flush=True)))
    return 0


if __name__ == "__main__":
    sys.exit(_child_main(sys.argv[1:]))
