"""Pure estimation maths for semfleet: SE(2), models, hybrid beliefs and metrics.

Nothing in this package performs I/O, reads a clock or starts a thread; randomness arrives as a
``numpy.random.Generator`` argument.
"""
