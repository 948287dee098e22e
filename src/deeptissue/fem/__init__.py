"""Nonlinear finite element core: Ogden tissue, rigid indenters and cast, rigid bone, Newton solver."""
