#!/usr/bin/env python3
"""Tally of a schemathesis NDJSON report: responses per operation by status and error code,
and every 5xx with its request. Usage: tally.py ndjson-*.ndjson"""

import base64
import collections
import json
import sys


def content(part: dict | None) -> bytes:
    part = part or {}
    if "$base64" in part:
        return base64.b64decode(part["$base64"])
    return (part.get("string") or "").encode()


def main(paths: list[str]) -> None:
    by_op: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    server_errors = []
    total = 0
    for path in paths:
        for line in open(path, encoding="utf-8"):
            event = json.loads(line)
            if "ScenarioFinished" not in event:
                continue
            recorder = event["ScenarioFinished"]["recorder"]
            for case_id, interaction in recorder.get("interactions", {}).items():
                response = interaction.get("response")
                case = recorder["cases"].get(case_id, {}).get("value", {})
                label = f"{case.get('method', '?')} {case.get('path', '?')}"
                if response is None:
                    by_op[label]["no response"] += 1
                    continue
                total += 1
                status = response["status_code"]
                body = content(response.get("content"))
                try:
                    code = json.loads(body)["error"]["code"]
                except Exception:
                    code = ""
                by_op[label][f"{status} {code}".strip()] += 1
                if status >= 500:
                    request = interaction["request"]
                    server_errors.append((status, request["method"], request["uri"],
                                          content(request.get("body"))[:500], body[:300]))
    print(f"{total} responses")
    # Undocumented methods (the unsupported_method check) answered 405 only: one line for all.
    probes = sorted(label for label, counts in by_op.items() if set(counts) == {"405 method_not_allowed"})
    for label in sorted(by_op):
        if label in probes:
            continue
        counts = ", ".join(f"{k}: {v}" for k, v in by_op[label].most_common())
        print(f"  {label}  {counts}")
    if probes:
        print(f"  {len(probes)} undocumented method/path pairs, all 405 method_not_allowed")
    print(f"{len(server_errors)} responses with a 5xx status")
    for status, method, uri, body, answer in server_errors[:50]:
        print(f"  {status} {method} {uri}\n    body: {body!r}\n    answer: {answer!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
