"""Bring your own patient: a CT label map or a surface mesh in, a prepared anatomy out.

* :mod:`~cgail_patient.synthetic` makes realistic synthetic label maps (and surface
  meshes) from the built-in anatomies, in a scanner frame, with the truth to compare against:
  the project's own test data (nothing is downloaded).
* :mod:`~cgail_patient.volume` reads the inputs (NIfTI, NRRD and 3D Slicer ``.seg.nrrd``
  label maps; STL/OBJ/PLY/VTP meshes) into one binary lumen volume in patient LPS millimetres.
* :mod:`~cgail_patient.prepare` is the pipeline: lumen, centreline skeleton, flat cuts,
  remeshing, caps, landmarks, the conversion to the ``phantom`` frame.
* :mod:`~cgail_patient.validate` checks the prepared anatomy (mesh, lumen radius against
  the catheter, bends against the catheter's bend radius, starts and introducers, a short
  deformable-wall run) and returns findings with one clear line each.
* :mod:`~cgail_patient.prepare_cli` is the console script ``prepare_anatomy``; it writes
  the prepared anatomy directory (``lumen.stl``, ``lumen.yaml``, ``prepare.yaml``,
  ``report.md``, ``render.png``).

Pure numpy/scipy/scikit-image/nibabel/pynrrd/trimesh: no rclpy, no torch.
"""

from cgail_sim.mesh_io import AnatomyError


class PatientError(AnatomyError):
    """An input cannot be made into a usable anatomy; the message says why in one line."""


__all__ = ["PatientError"]
