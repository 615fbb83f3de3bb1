"""Optimizers: adapters over nlopt and scipy (library.py) and the loops of SQP and MMA
(loops.py, mma.py). They know nothing of mechanisms: they see functions of a design vector.
"""
