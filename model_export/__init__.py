"""xyzcyl.model_export"""
