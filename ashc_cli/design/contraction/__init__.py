"""Contraction certificates: the first box of the paper's flow chart (eq. (28), Theorem 1), one method a module.

* :mod:`.terms`: the Jacobian df/dx over state_box x U written as A0 + sum_k theta_k(x, u) A_k over the plant's
  distinct scalar nonlinear terms, each theta_k enclosed by ball arithmetic;
* :mod:`.vertex`: the LMI at a finite set of matrices (vertices of U, or corners of the box of term values);
* :mod:`.feedback`: the same with a synthesised gain K, the smallest the rate allows;
* :mod:`.proof`: the vertex argument in ball arithmetic (an arb Cholesky per vertex);
* :mod:`.precheck`: before any LMI, a sampled state where no M (no K) can work refutes the rate in seconds.

The stage :mod:`ashc_cli.design.stages.stabilise` chooses among them and records which it used.
"""
