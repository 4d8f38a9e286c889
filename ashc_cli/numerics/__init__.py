"""The numerics the design proves with: arb ball arithmetic over boxes (:mod:`.interval`), the proofs built
on it (:mod:`.proofs`), Chebyshev series (:mod:`.chebyshev`) and small linear algebra (:mod:`.linalg`).
Reads the problem floor, nothing above it."""
