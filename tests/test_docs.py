"""The documentation: the site builds with warnings as errors (the documented command), its links and images resolve,
it speaks of the package rather than of a work queue, its result files are each cited by a page, and the README stays
short."""

import fnmatch
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).parents[1]
DOCS = ROOT / "docs"
README_MAX_WORDS = 700
RESULTS_MAX_WORDS = 2500


def pages() -> list[pathlib.Path]:
    """README.md and every Markdown page under docs/ (not the built site)."""
    return [ROOT / "README.md", *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.relative_to(DOCS).parts)]


def without_code_blocks(text: str) -> str:
    return re.sub(r"^(```|~~~).*?^\1", "", text, flags=re.DOTALL | re.MULTILINE)


def prose(text: str) -> str:
    """The text a reader sees as Markdown: fenced code blocks and inline code removed."""
    return re.sub(r"`[^`\n]*`", "", without_code_blocks(text))


LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")  # link text may wrap lines


def anchors(page: pathlib.Path) -> set[str]:
    """The anchors MyST gives a page's headings (``myst_heading_anchors = 3``; GitHub's slugs, for the README)."""
    found = set()
    text = without_code_blocks(page.read_text())
    for level, title in re.findall(r"^(#{1,6})\s+(.+?)\s*#*\s*$", text, flags=re.MULTILINE):
        if len(level) <= 3:
            found.add(re.sub(r"[^\w\- ]", "", title.replace("`", "").strip().lower()).replace(" ", "-"))
    return found


def broken_links(page: pathlib.Path, root: pathlib.Path = ROOT) -> list[str]:
    """Relative links and images of a page whose file (or heading anchor, in a Markdown page) does not exist."""
    broken, name = [], page.relative_to(root)
    for target in LINK.findall(prose(page.read_text())):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, flags=re.IGNORECASE):  # http(s):, mailto:, ...
            continue
        path, _, anchor = target.partition("#")
        if not path:  # an anchor of the page itself
            continue
        resolved = (page.parent / path).resolve()
        if not resolved.exists():
            broken.append(f"{name}: {target} (no such file)")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{name}: {target} (no such heading)")
    return broken


ISSUE = re.compile(r"\b(?:issues?|PRs?|pull requests?)\s*#?\s*\d+\b|(?<![\w&/#])#\d+\b", flags=re.IGNORECASE)


def issue_references(page: pathlib.Path) -> list[str]:
    """References to the work queue: "issue 13", "Issue #31", "PR 7", "#18" (code included)."""
    return [
        f"{page.relative_to(ROOT)}:{number}: {match.group(0)}"
        for number, line in enumerate(page.read_text().splitlines(), 1)
        for match in ISSUE.finditer(line)
    ]


RESULT_PATH = re.compile(r"(?:\.\./)*(?:docs/)?results/[\w./{},*-]*")


def expand_braces(pattern: str) -> list[str]:
    """A shell pattern's brace alternatives, expanded: ``a_{b,c}*`` -> ``a_b*``, ``a_c*``."""
    match = re.search(r"\{([^{}]*)\}", pattern)
    if match is None:
        return [pattern]
    head, tail = pattern[: match.start()], pattern[match.end() :]
    return [expanded for option in match.group(1).split(",") for expanded in expand_braces(head + option + tail)]


def cited_results(page: pathlib.Path) -> list[tuple[str, bool]]:
    """The paths under docs/results a page names (links, commands, prose), each with whether it is a glob (``*``,
    ``{a,b}``, or a name cut at ``_``) rather than a whole path; braces expanded, so one entry per alternative."""
    cited = []
    for match in RESULT_PATH.finditer(page.read_text()):
        name = match.group(0).rstrip(".,")
        if name.count("{") != name.count("}"):
            name = name[: name.index("{")] + "*"  # a brace group the match cut: as wide as it could be
        if name.startswith("docs/"):
            base = ROOT
        elif name.startswith(("results/", "../")):
            base = page.parent
        else:  # "results/..." inside a longer word
            continue
        for expanded in expand_braces(name + ("*" if name.endswith("_") else "")):
            glob = "*" in expanded
            path = pathlib.Path(os.path.normpath(base / expanded))
            if DOCS / "results" in [path, *path.parents]:
                cited.append((str(path), glob))
    return cited


def test_docs_build_without_warnings(tmp_path):
    command = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(DOCS), str(tmp_path)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-5000:]
    built = {path.stem for path in tmp_path.glob("*.html")}
    assert {"index", "install", "quickstart", "algorithm", "representations", "history", "zoo", "diagnostics",
            "benchmarks", "api", "changelog", "results-ppo-settings",
            "results-paper-protocol"} <= built  # fmt: skip
    notes = {path.stem for path in (tmp_path / "notes").glob("*.html")}
    assert "index" in notes and {path.stem for path in (DOCS / "notes").glob("*.md")} <= notes
    api = (tmp_path / "api.html").read_text()
    assert "sb3_pevfa.PPOPeVFA" in api and "predict_values" in api  # autodoc found the docstrings


def test_relative_links_and_images_resolve():
    broken = [entry for page in pages() for entry in broken_links(page)]
    assert not broken, "\n".join(broken)


def test_link_checker_catches_what_it_should(tmp_path):
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# Other\n\n## A heading, with `code`\n")
    page.write_text(
        "[fine](other.md#a-heading-with-code) [web](https://example.org/x) [anchor](#top) ![img](missing.png)\n"
        "[gone](nothere.md) [bad anchor](other.md#nope) `[in code](ignored.md)`\n```\n[in a block](ignored.md)\n```\n"
        "[a wrapped\nlink](wrapped.md)\n"
    )
    assert broken_links(page, root=tmp_path) == [
        "page.md: missing.png (no such file)", "page.md: nothere.md (no such file)",
        "page.md: other.md#nope (no such heading)", "page.md: wrapped.md (no such file)",
    ]  # fmt: skip


def test_no_issue_references():
    found = [entry for page in pages() for entry in issue_references(page)]
    assert not found, "the documentation speaks of the package, not of the work queue:\n" + "\n".join(found)
    samples = ["issue 13's tests", "Issue #31", "issues 13, 18", "PR 7", "see #18.", "(#4)"]
    assert all(ISSUE.search(sample) for sample in samples)
    assert not any(ISSUE.search(s) for s in ["pevfa-opr-history-40k", "seed 2", "[x](a.md#b1)", "&#8203;", "#L12"])


def test_readme_is_short():
    words = len((ROOT / "README.md").read_text().split())
    assert words <= README_MAX_WORDS, f"README.md has {words} words (at most {README_MAX_WORDS})"


def words(text: str) -> int:
    """Words a reader reads: tokens with a letter or a digit outside code blocks (not a table's pipes and rules)."""
    return sum(1 for token in without_code_blocks(text).split() if re.search(r"[^\W_]", token))


def with_includes(page: pathlib.Path) -> str:
    """A page's text with the files its MyST ``{include}`` directives pull in."""
    text = page.read_text()
    for target in re.findall(r"^```\{include\}\s+(\S+)", text, flags=re.MULTILINE):
        text += "\n" + (page.parent / target).read_text()
    return text


def test_results_pages_are_short():
    counts = {page.name: words(with_includes(page)) for page in sorted(DOCS.glob("results-*.md"))}
    assert 1 <= len(counts) <= 3 and sum(counts.values()) <= RESULTS_MAX_WORDS, counts  # no budget split over more pages
    assert words("| a | 12 ± 3 |\n|---|---|\n```bash\nnot counted\n```\n") == 3


def test_results_pages_lead_with_one_plain_sentence():
    """A newcomer reads what a results page shows before its statistics: its first paragraph is one sentence in
    words (no IQM, CI or table) after "In short:"."""
    for page in sorted(DOCS.glob("results-*.md")):
        first = page.read_text().split("\n\n")[1]
        assert first.startswith("**In short:** "), page.name
        assert first.count(". ") == 0 and first.rstrip().endswith("."), page.name
        assert not any(term in first for term in ("IQM", "CI", "|", "±")), page.name


def test_every_result_file_is_cited_and_every_cited_result_exists():
    """Each file under docs/results is named by a page (itself, a folder above it, or a glob that matches it); each
    path a page names there exists, and each glob matches a file."""
    results = DOCS / "results"
    files = sorted(str(path) for path in results.rglob("*") if path.is_file())
    cited = [entry for page in pages() for entry in cited_results(page)]
    missing = sorted({path for path, glob in cited if not glob and not pathlib.Path(path).exists()})
    assert not missing, "named by a page but absent:\n" + "\n".join(missing)
    globs = {path for path, glob in cited if glob}
    dangling = sorted(glob for glob in globs if not any(fnmatch.fnmatchcase(f, glob) for f in files))
    assert not dangling, "globs that match nothing:\n" + "\n".join(dangling)
    # a whole protocol's or note's folder, named in prose, cites none of its files; a glob in it does
    folders = [results, results / "notes"]
    broad = {str(p) for p in (*folders, *(path for folder in folders for path in folder.iterdir() if path.is_dir()))}
    named = {path for path, glob in cited if not glob and path not in broad}

    def is_cited(file: str) -> bool:
        return any(file == path or file.startswith(path + os.sep) for path in named) or any(
            fnmatch.fnmatchcase(file, glob) for glob in globs
        )

    orphans = [str(pathlib.Path(file).relative_to(ROOT)) for file in files if not is_cited(file)]
    assert not orphans, "files under docs/results that no page names:\n" + "\n".join(orphans)
    assert expand_braces("a_{b,c}_{d,e}*") == ["a_b_d*", "a_b_e*", "a_c_d*", "a_c_e*"]


def table_rows(text: str) -> dict[str, list[str]]:
    """A Markdown text's table rows by their first cell, each cell stripped of a run count in brackets."""
    rows = {}
    for line in text.splitlines():
        cells = [re.sub(r"\s*\(\d+\)$", "", cell.strip()) for cell in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) > 1 and not set(cells[0]) <= set("-: "):
            rows[cells[0]] = cells[1:]
    return rows


def test_readme_results_table_is_the_report_s():
    """The README's results table is the summary of the protocol whose curves it shows, cell for cell (the summary's
    columns after the README's last one, the run counts and the other protocols' ratios, left out)."""
    readme = (ROOT / "README.md").read_text()
    folder = re.search(r"\]\((docs/results/[\w-]+)/curves\.png\)", readme).group(1)
    summary = table_rows((ROOT / folder / "summary.md").read_text())
    readme_rows = {task: cells for task, cells in table_rows(readme).items() if task.endswith(("-v3", "-v5"))}
    assert len(readme_rows) == 6, readme_rows
    for task, cells in readme_rows.items():
        assert summary[task][: len(cells)] == cells, (task, cells, summary[task])
    assert table_rows("| a | 1 ± 2 (5) | 3x |\n|---|---|---|\n") == {"a": ["1 ± 2", "3x"]}


def test_the_off_policy_argument_tables_list_every_pevfa_argument_with_its_default():
    """docs/off-policy.md's tables: each PeVFA argument of SACPeVFA / TD3PeVFA and of their policies, with the
    default the code has (a string as ``"opr"``, a class as ``nn.ReLU``), and no argument that does not exist."""
    import inspect

    from sb3_pevfa.pevfa.off_policy import OffPolicyPeVFA
    from sb3_pevfa.pevfa.q_critics import PeVFAQPolicyMixin

    def shown(value) -> str:
        if inspect.isclass(value):
            return f"nn.{value.__name__}"
        return f'"{value}"' if isinstance(value, str) else repr(value)

    documented = {
        name.strip("`"): cells[0].strip("`")
        for name, cells in table_rows((DOCS / "off-policy.md").read_text()).items()
        if name.startswith("`")
    }
    expected = {}
    for function in (OffPolicyPeVFA.__init__, PeVFAQPolicyMixin.__init__):
        for parameter in inspect.signature(function).parameters.values():
            public = not parameter.name.startswith("_") and parameter.name != "policy_kwargs"
            if parameter.default is not parameter.empty and public:
                expected[parameter.name] = shown(parameter.default)
    assert documented == expected
    assert table_rows("| `a` | `(64,)` | x |\n|---|---|---|\n") == {"`a`": ["`(64,)`", "x"]}


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _installed_by(extras: list[str]) -> set[str]:
    """The distributions ``pip install -e ".[extras]"`` installs: the package's requirements and those of the extras,
    with their own requirements (what this environment's metadata says)."""
    import importlib.metadata as md

    from packaging.requirements import Requirement

    seen, stack = set(), [("sb3-pevfa", tuple(extras))]
    while stack:
        name, wanted = stack.pop()
        if (_canonical(name), wanted) in seen:
            continue
        seen.add((_canonical(name), wanted))
        try:
            requires = md.distribution(name).requires or []
        except md.PackageNotFoundError:  # a requirement of another platform
            continue
        for line in requires:
            requirement = Requirement(line)
            marker = requirement.marker
            if marker is None or any(marker.evaluate({"extra": extra}) for extra in (*wanted, "")):
                stack.append((requirement.name, tuple(sorted(requirement.extras))))
    return {name for name, _ in seen}


def _documented_modules() -> str:
    """The modules docs/api.md documents (an ``autoclass``'s module)."""
    found = re.findall(r"^\.\. (auto\w+):: ([\w.]+)", (DOCS / "api.md").read_text(), flags=re.MULTILINE)
    return " ".join(sorted({name if kind == "automodule" else name.rpartition(".")[0] for kind, name in found}))


@pytest.mark.parametrize(
    "page, line, imports",
    [
        ("README.md", r"pip install -e \.(?:\[([\w,]+)\])? && python examples/train_pevfa\.py", "examples/train_pevfa.py"),
        ("README.md", r"The benchmarks .*?pip install -e \"\.\[([\w,]+)\]\"", "engine.commands engine.report"),
        ("docs/install.md", r"pip install -e \"\.\[([\w,]+)\]\" && python -m sphinx", "docs/api.md"),
    ],
)
def test_the_install_lines_bring_what_their_code_imports(page: str, line: str, imports: str):
    """The main job's example, the benchmark scripts and the modules the API page documents import with only what
    their install line installs: a subprocess where every module of another installed distribution is missing (this
    environment holds the tests' extras too, so a plain import would not tell; optional imports stay optional)."""
    import importlib.metadata as md

    found = re.search(line, (ROOT / page).read_text())
    assert found, f"no line {line!r} in {page}"
    imports = _documented_modules() if imports == "docs/api.md" else imports
    installed = _installed_by(found[1].split(",") if found[1] else [])
    missing = sorted(module for module, dists in md.packages_distributions().items()
                     if module.isidentifier() and not {_canonical(d) for d in dists} & installed)  # fmt: skip
    assert "pytest" in missing and "sb3_pevfa" not in missing  # the test's own, and the package
    code = (
        "import importlib.abc, importlib.util, sys\n"
        "missing = set(sys.argv[1].split(','))\n"
        "class NotInstalled(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.partition('.')[0] in missing:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, NotInstalled())\n"
        "sys.path.insert(0, 'benchmarks')\n"
        "for target in sys.argv[2:]:\n"
        "    if target.endswith('.py'):  # a script: its imports, not its main\n"
        "        spec = importlib.util.spec_from_file_location('script', target)\n"
        "        spec.loader.exec_module(importlib.util.module_from_spec(spec))\n"
        "    else:\n"
        "        __import__(target)\n"
    )
    result = subprocess.run([sys.executable, "-c", code, ",".join(missing), *imports.split()], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)  # fmt: skip
    assert result.returncode == 0, result.stderr[-1500:]
