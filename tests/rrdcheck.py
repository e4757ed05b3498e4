"""Reading a recording back with Rerun's own reader, and holding a blueprint's views to it."""

from collections import defaultdict


def recorded(path) -> tuple[dict, dict]:
    """(entity -> {component: rows with data on a timeline}, entity -> {static components})."""
    import rerun as rr

    rows: dict = defaultdict(lambda: defaultdict(int))
    static: dict = defaultdict(set)
    for chunk in rr.chunk.RrdReader(str(path)).stream().to_chunks():
        e = str(chunk.entity_path)
        names = [n for n in chunk.to_record_batch().schema.names if ":" in n]
        if chunk.is_static:
            static[e].update(names)
        else:
            for n in names:
                rows[e][n] += chunk.num_rows
    return rows, static


def matches(query: str, entity: str) -> bool:
    if query.endswith("/**"):
        base = query[:-3]
        return entity == base or entity.startswith(base + "/") or base == ""
    return entity == query


def view_problems(views, rows, static) -> list[str]:
    """Every view must match at least one entity with data of its kind; every query matches some
    entity; queries use no `*` but a trailing `/**`; every series that has a name has data."""
    probs = []
    for v in views:
        for q in v.contents:
            if "*" in (q[:-3] if q.endswith("/**") else q):
                probs.append(f"{v.name}: query {q!r} uses '*' other than a trailing '/**'")
        for q in v.contents:
            if not any(matches(q, e) for e in set(rows) | set(static)):
                probs.append(f"{v.name}: query {q!r} matches no entity of the recording")
        hit = [e for e in rows if any(matches(q, e) for q in v.contents) and rows[e].get(v.data, 0) > 0]
        if not hit:
            probs.append(f"view {v.name!r} ({', '.join(v.contents)}): no entity with {v.data} data")
    for e, comps in static.items():
        if any(c.startswith("SeriesLines:names") for c in comps) and not rows.get(e, {}).get("Scalars:scalars"):
            probs.append(f"series {e} has a name but no data")
    return probs
