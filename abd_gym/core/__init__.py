"""Building blocks below the physics: Warp operations made once per scalar type, launches and graphs,
devices, and the float64 NumPy references of affine kinematics and joint angles."""
