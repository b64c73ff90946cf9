"""Privacy you can verify: the transcript audit, transcript-only attacks, and the privacy report.

Client-side code: the audit reads raw values from the run store to compare them with what was
sent. The attacks read only what the provider saw (the recorded request bodies) plus public
knowledge of the task, and the simulator attacks a public env; their results are compared with
the secrets only afterwards, in the report and the audit.
"""
