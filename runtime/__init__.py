"""xyzcyl.runtime"""
