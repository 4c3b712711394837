"""xyzcyl.clients"""
