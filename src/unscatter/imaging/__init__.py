"""Registration and thresholding of fluorescence images of prints (stage 'registration').

A microscope image shows a print at an unknown rotation, scale and offset, under
vignetting, background and noise, with no fiducial marks. For each print of a batch:

1. **Flat field and background** (``flatfield``): the camera offset is subtracted and
   the image divided by a smooth background surface, so polymer fluorescence is in
   units of the local background, comparable between the prints of a batch.
2. **One threshold per batch** (``flatfield.dense_level``): the print is where polymer
   density is at least ``level`` times that of dense, fully cured polymer, that level
   estimated once for the whole batch (in a batch that stains, again on its images with
   the stain divided out, before the empty and faint test). An image with nothing above it is **empty**.
3. **Pose** (``pose``): several distinct coarse poses, each refined by Gauss-Newton
   against the batch's print template (``template``) with the print's own dose, gain
   and offset; the moves under which the predicted print maps onto itself (a grating's
   pitch, a star's spokes) are tried as well, and the pose the image prefers over
   every distinct rival is kept. When a rival fits almost as well the print is
   ``failed`` as **ambiguous**; so it is when a rival a period along (a grating that
   spans the field and cured in part of it) lays the same mask over every part that
   cured, so that only where the template puts the lamp's field sets the two apart
   (``batch.mask_apart``). A rival that leaves a printed part unexplained, or predicts
   one where the image shows none, while the best pose explains the image there, is
   set aside (``pose.contradicted``: a print of a few dots spans too few blocks for the
   evidence to decide).
4. **QC** (``batch``): rotation and scale in range, refinement converged, template
   correlation at least ``min_score``, the print inside the image, the evidence over
   rivals. A print that fails is marked ``failed`` in qc.tsv with the reason and no
   print is written for it.
"""

from .batch import MARGIN, RegistrationError, Settings, register_batch, threshold_print, warp_to_design
from .flatfield import Corrected, correct_image, dense_level, fit_background
from .pose import pose_of, project_similarity, transform_rms_px
from .stack import register_stacks
from .template import PrintTemplate, ncc

__all__ = ["MARGIN", "RegistrationError", "Settings", "register_batch", "register_stacks", "threshold_print", "warp_to_design", "Corrected",
           "correct_image", "dense_level", "fit_background", "pose_of", "project_similarity", "transform_rms_px",
           "PrintTemplate", "ncc"]
