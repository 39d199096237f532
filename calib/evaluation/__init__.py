"""Evaluation (paper §III-F-3, §IV): ``cross_validation`` the folds and Tables I–II;
``reconstruct`` the cone and prism reconstruction with ICP (Table III)."""
