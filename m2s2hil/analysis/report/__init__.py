"""What an evaluation or a session is written as: the evaluation's report folder
(``evaluation_files``), its charts (``charts``) and a session's HTML QC report and contact
sheet (``session_html``).
"""
