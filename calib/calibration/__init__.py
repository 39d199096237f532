"""Calibration (paper §III-F): ``T_ee_us`` from what was localized.

``markers`` the single- and three-marker fit (§III-F-1/2); ``alternation`` the
alternation of localization and calibration (§III-F); ``nwire`` the same unknowns from
N-wire patterns (PLUS's phantom); ``targets`` any mix of target kinds in one fit;
``uncertainty`` the 95 % bounds; ``verdict`` accepted / suspect / rejected with reasons.
"""
