"""The bone: CT import (:mod:`~dhg.bone.ct`), the synthetic femur phantoms
(:mod:`~dhg.bone.phantom`), X-ray images (:mod:`~dhg.bone.xray`) and what the planning CT shows
along the path (:mod:`~dhg.bone.planning`). The voxel volume itself is :class:`dhg.Volume`."""
