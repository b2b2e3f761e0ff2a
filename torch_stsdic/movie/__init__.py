"""movie"""
