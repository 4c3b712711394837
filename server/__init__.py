"""xyzcyl.server"""
