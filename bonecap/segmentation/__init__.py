"""MRI segmentation, slice by slice (Kojima et al.): the body and its skin (:mod:`.skin`), long bones by
the cortical-edge rule (:mod:`.cortical`), other bones by the density-threshold rule (:mod:`.density`),
the per-bone driver that labels every bone of a station from its seeds (:mod:`.bones`), MRI-visible
capsules (:mod:`.capsules`), the discs along the spinal column (:mod:`.spine`) and, after the warp, the density
rule's bones refined from the personal skeleton's sections by the image (:mod:`.refine`)."""
