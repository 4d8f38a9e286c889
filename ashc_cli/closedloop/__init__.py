"""The closed loop: the plant, the abstraction, the interface and the abstract controller integrated together,
compiled with numba (:mod:`.compiled` for simulate's tracking and m-relation runs, :mod:`.falsify_loop` for
falsify's batches).  Reads the problem and numerics floors."""
