"""The packing result of a scan (LR-NBV paper, section 4.1): the object's oriented bounding box, its IoU
with the ground truth in sim, surface coverage, poses and useless poses, and a container choice."""
