"""`python -m app solve PROBLEM.json --out RESULT.json` (filled in with the solver)."""


def register(sub):
    p = sub.add_parser("solve", help="solve a game described in a JSON problem file")
    p.add_argument("problem")
    p.add_argument("--out")
    p.set_defaults(func=lambda a: 0)
