"""The design: the stages of the paper's flow chart (Fig. 3), one module each in :mod:`.stages`, the
contraction certificates of the first stage (:mod:`.contraction`), the HDF5 artefacts they write
(:mod:`.artefacts`), the order they run in (:mod:`.pipeline`) and the verdict on Problem 1 (:mod:`.verdict`).
Stages read each other's artefacts (through :mod:`.upstream`), never each other's modules."""
