"""Formulas of a photo pair: space intersection, absolute orientation (7-parameter similarity), space
resection, and the model of an oriented pair (model points and their absolute orientation).
"""
