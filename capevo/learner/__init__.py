"""Learners: turn experience into candidate ECM versions (they publish; the gate promotes).

Code side: :mod:`.skills` (built-in v0 code skills), :mod:`.search` (CEM over PARAMS),
:mod:`.synthesis` (LLM code edits), :mod:`.hybrid` (LLM edit + CEM), with the shared
:mod:`.base` (request, candidate, scores), :mod:`.experience` (traces -> which ECM to fix),
:mod:`.scratch` (run unpublished candidates) and :mod:`.chat` (the chat endpoint).
"""
