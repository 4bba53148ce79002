"""Pure-torch geometry ops: SE(3) helpers, rotated BEV IoU, NMS."""
