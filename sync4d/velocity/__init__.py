"""Delta-velocity fields (group ``velocity``, paper Sec. 3.4): ``dv = field(x, part)`` added to the reference's
velocities; ``triplane`` and ``per_part`` are trained by the transfer, ``none`` adds nothing."""
