"""Symbolic terms and candidate libraries: CasADi symbols and their sympy forms, the term parser (text read
as data), :class:`~symsbl.Term` and :class:`~symsbl.Library`, the term builders and the compiled evaluator."""
