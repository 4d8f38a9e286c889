"""The paper's numbering: its LaTeX labels as the published paper numbers them, and :func:`cite`, which rewrites
text that quotes a label ("eq. SimuFuncCondi1" -> "eq. (6)").  The code cites the numbers (a test keeps labels out of
it); docs/theory.md keeps both.

The table is docs/labels.json (counted from the paper's source, see docs/theory.md); a test keeps the two equal.
"""

from __future__ import annotations

import re

__all__ = ["LABELS", "cite"]

#: label -> how the paper numbers it ("eq. (6)", "Theorem 2", "Fig. 5", "Section III-A", ...).
LABELS: dict[str, str] = {
    'intro': 'Section I',
    'Hierarchical_Structure': 'Fig. 1',
    'prelimiaries': 'Section II',
    'ControlSystem': 'Definition 1',
    'ConcreteSystem': 'eq. (1)',
    'AbstractSystem': 'eq. (2)',
    'stabilisab': 'Definition 2',
    'funcff': 'eq. (3)',
    'trajConverge': 'eq. (4)',
    'StabiliseLyap': 'Theorem 1',
    'stabilisableV': 'eq. (5)',
    'stabilisableCond1': 'eq. (5a)',
    'stabilisableCond2': 'eq. (5b)',
    'formulate': 'Section III',
    'BODintro': 'Section III-A',
    'simuFunction': 'Definition 3',
    'SimuFuncCondi1': 'eq. (6)',
    'SimuFuncCondi2': 'eq. (7)',
    'ErrorBound': 'Theorem 2',
    'TrackConst': 'eq. (9)',
    'SimuLocalRequire': 'eq. (10)',
    'mRelat': 'Definition 4',
    'mRelatDiff': 'eq. (11a)',
    'mRelatOut': 'eq. (11b)',
    'mRelatOutMatch': 'Theorem 3',
    'ASHC': 'Problem 1',
    'solution': 'Section IV',
    'abstractAffine': 'eq. (12)',
    'concreteAffine': 'eq. (13)',
    'BODdesign': 'Section IV-A',
    'outputLipstchiz': 'Assumption 1',
    'SimuDesign': 'Theorem 4',
    'SimuDesignCond1': 'eq. (14a)',
    'SimuDesignCond2': 'eq. (14b)',
    'Interface': 'eq. (15)',
    'SimuResBound': 'eq. (16)',
    'condB': 'Proposition 1',
    'bounddVdx': 'eq. (17)',
    'SimuResBoundYoung': 'eq. (18)',
    'uMinBound': 'eq. (20)',
    'LinearCompare': 'Remark 3',
    'SimuNotAffine': 'Remark 4',
    'solvePDE': 'Remark 5',
    'mRelateDesign': 'Section IV-B',
    'mRelatePDE': 'Lemma 1',
    'mRelatSuffi': 'eq. (21)',
    'mRelatSuffiDiff': 'eq. (21a)',
    'mRelatSuffiIn': 'eq. (21b)',
    'mRelatSuffiOut': 'eq. (21c)',
    'mRelateLink': 'eq. (22)',
    'mRelateInterconnect': 'Fig. 2',
    'mRelateDelta': 'Theorem 5',
    'Flow_Chart': 'Fig. 3',
    'RelateMM': 'Remark 6',
    'steps': 'Section IV-C',
    'mCondi': 'Theorem 6',
    'mRelationImP': 'eq. (23)',
    'mRelateGeo': 'Corollary 1',
    'GeoCondi': 'eq. (24)',
    'example': 'Section V',
    'Converter_Circuit': 'Fig. 4',
    'ConverterAveMod': 'eq. (25)',
    'ConvertSystem': 'eq. (26)',
    'ConvertSystemLinear': 'eq. (27)',
    'parameter': 'Table I',
    'egLMI': 'eq. (28)',
    'egM': 'eq. (29)',
    'egV': 'eq. (30)',
    'egSimuDesign': 'eq. (31)',
    'egKappa': 'eq. (32)',
    'mEquation': 'eq. (33)',
    'egm': 'eq. (34)',
    'kappa_xi': 'Fig. 5',
    'egSimuFunc': 'eq. (35)',
    'egConditionB': 'eq. (36)',
    'iota': 'eq. (37)',
    'delta_Compare': 'Fig. 6',
    'egErrorBound': 'eq. (38)',
    'egDelta': 'eq. (39)',
    'egMrelateLink': 'eq. (40)',
    'egAbstract': 'eq. (41)',
    'egInterface': 'eq. (42)',
    'egqLS': 'eq. (43)',
    'egInterfaceSat': 'eq. (44)',
    'Example_BoundedIn': 'Fig. 7',
    'Example_BoundedOut': 'Fig. 8',
    'Example_mRelationIn': 'Fig. 9',
    'Example_mRelationOut': 'Fig. 10',
    'concl': 'Section VI',
    'sec:intro': 'Section I',
    'fig:Hierarchical_Structure': 'Fig. 1',
    'sec:prelimiaries': 'Section II',
    'def:ControlSystem': 'Definition 1',
    'equ:ConcreteSystem': 'eq. (1)',
    'equ:AbstractSystem': 'eq. (2)',
    'def:stabilisab': 'Definition 2',
    'equ:funcff': 'eq. (3)',
    'equ:trajConverge': 'eq. (4)',
    'thm:StabiliseLyap': 'Theorem 1',
    'equ:stabilisableV': 'eq. (5)',
    'equ:stabilisableCond1': 'eq. (5a)',
    'equ:stabilisableCond2': 'eq. (5b)',
    'sec:formulate': 'Section III',
    'subsec:BODintro': 'Section III-A',
    'def:simuFunction': 'Definition 3',
    'equ:SimuFuncCondi1': 'eq. (6)',
    'equ:SimuFuncCondi2': 'eq. (7)',
    'thm:ErrorBound': 'Theorem 2',
    'equ:ErrorBound': 'eq. (8)',
    'equ:TrackConst': 'eq. (9)',
    'equ:SimuLocalRequire': 'eq. (10)',
    'def:mRelat': 'Definition 4',
    'equ:mRelat': 'eq. (11)',
    'equ:mRelatDiff': 'eq. (11a)',
    'equ:mRelatOut': 'eq. (11b)',
    'thm:mRelatOutMatch': 'Theorem 3',
    'prob:ASHC': 'Problem 1',
    'sec:solution': 'Section IV',
    'equ:abstractAffine': 'eq. (12)',
    'equ:concreteAffine': 'eq. (13)',
    'subsec:BODdesign': 'Section IV-A',
    'asmp:outputLipstchiz': 'Assumption 1',
    'thm:SimuDesign': 'Theorem 4',
    'equ:SimuDesign': 'eq. (14)',
    'equ:SimuDesignCond1': 'eq. (14a)',
    'equ:SimuDesignCond2': 'eq. (14b)',
    'equ:Interface': 'eq. (15)',
    'equ:SimuResBound': 'eq. (16)',
    'prop:condB': 'Proposition 1',
    'equ:bounddVdx': 'eq. (17)',
    'equ:SimuResBoundYoung': 'eq. (18)',
    'equ:uMinBound': 'eq. (20)',
    'rmk:LinearCompare': 'Remark 3',
    'rmk:SimuNotAffine': 'Remark 4',
    'rmk:solvePDE': 'Remark 5',
    'subsec:mRelateDesign': 'Section IV-B',
    'lem:mRelatePDE': 'Lemma 1',
    'equ:mRelatSuffi': 'eq. (21)',
    'equ:mRelatSuffiDiff': 'eq. (21a)',
    'equ:mRelatSuffiIn': 'eq. (21b)',
    'equ:mRelatSuffiOut': 'eq. (21c)',
    'equ:mRelateLink': 'eq. (22)',
    'fig:mRelateInterconnect': 'Fig. 2',
    'thm:mRelateDelta': 'Theorem 5',
    'fig:Flow_Chart': 'Fig. 3',
    'rmk:RelateMM': 'Remark 6',
    'subsec:steps': 'Section IV-C',
    'thm:mCondi': 'Theorem 6',
    'equ:mRelationImP': 'eq. (23)',
    'corol:mRelateGeo': 'Corollary 1',
    'equ:GeoCondi': 'eq. (24)',
    'sec:example': 'Section V',
    'fig:Converter_Circuit': 'Fig. 4',
    'equ:ConverterAveMod': 'eq. (25)',
    'equ:ConvertSystem': 'eq. (26)',
    'equ:ConvertSystemLinear': 'eq. (27)',
    'tab:parameter': 'Table I',
    'equ:egLMI': 'eq. (28)',
    'equ:egM': 'eq. (29)',
    'equ:egV': 'eq. (30)',
    'equ:egSimuDesign': 'eq. (31)',
    'equ:egKappa': 'eq. (32)',
    'equ:mEquation': 'eq. (33)',
    'equ:egm': 'eq. (34)',
    'fig:kappa_xi': 'Fig. 5',
    'equ:egSimuFunc': 'eq. (35)',
    'equ:egConditionB': 'eq. (36)',
    'equ:iota': 'eq. (37)',
    'fig:delta_Compare': 'Fig. 6',
    'equ:egErrorBound': 'eq. (38)',
    'equ:egDelta': 'eq. (39)',
    'equ:egMrelateLink': 'eq. (40)',
    'equ:egAbstract': 'eq. (41)',
    'equ:egInterface': 'eq. (42)',
    'equ:egqLS': 'eq. (43)',
    'equ:egInterfaceSat': 'eq. (44)',
    'fig:Example_BoundedIn': 'Fig. 7',
    'fig:Example_BoundedOut': 'Fig. 8',
    'fig:Example_mRelationIn': 'Fig. 9',
    'fig:Example_mRelationOut': 'Fig. 10',
    'sec:concl': 'Section VI',
}

_KINDS = r"eqs?\.|Thm\.|Theorem|Prop\.|Proposition|Cor\.|Corollary|Def\.|Definition|Assumption|Lemma|Remarks?|Figs?\.|Section"
_ITEM = r"(?!(?:eqs?|Thm|Prop|Cor|Def|Figs?)\.)[A-Za-z_][A-Za-z0-9_]*(?:/[A-Za-z0-9_]+)?"
_CITATION = re.compile(rf"\b({_KINDS})\s+({_ITEM}(?:(?:, | and ){_ITEM})*)")
_PLURAL = {"eq.": "eqs.", "Fig.": "Figs."}


def _expand(item: str) -> list[str]:
    """"Example_BoundedIn/Out" -> the labels Example_BoundedIn and Example_BoundedOut (when both exist)."""
    if "/" not in item:
        return [item]
    head, tail = item.split("/", 1)
    for cut in range(len(head) - 1, 0, -1):
        if head[:cut] + tail in LABELS:
            return [head, head[:cut] + tail]
    return [item]


def cite(text: str) -> str:
    """``text`` with every citation of known labels written as the paper numbers it.

    "eq. SimuFuncCondi1" -> "eq. (6)"; "Thm. mCondi (ii), Cor. mRelateGeo" -> "Theorem 6 (ii), Corollary 1";
    "eqs. mRelatSuffiDiff, mRelatSuffiIn" -> "eqs. (21a), (21b)".  Words after the labels ("step 1") and
    unknown names are left as they are.

    Parameters
    ----------
    text : str

    Returns
    -------
    str
    """

    def replace(match: re.Match) -> str:
        items = re.split(r"(, | and )", match.group(2))
        names, rest = [], ""
        for k in range(0, len(items), 2):
            expanded = _expand(items[k])
            if all(e in LABELS for e in expanded):
                names.extend(expanded)
            else:
                rest = "".join(items[k - 1:]) if k else "".join(items)
                break
        if not names:
            return match.group(0)
        values = [LABELS[n] for n in names]
        if len(values) == 1:
            out = values[0]
        else:
            kind = values[0].split(" ", 1)[0]
            numbers = [v.split(" ", 1)[1] if v.split(" ", 1)[0] == kind else v for v in values]
            out = f"{_PLURAL.get(kind, kind + 's')} {', '.join(numbers)}"
        return out + rest

    return _CITATION.sub(replace, text)
